"""The joint IEEE 952 fit on real long static captures (tests/data/adis16405-static: 2.8 h of a
quantized ADIS16405; tests/data/mtig-static-contaminated: 1.4 h of an XSens MTi-G gyro).

Every expected value comes from an analysis written here with plain numpy: the fully
overlapping Allan deviation at the taus the pipeline reports, the white-noise level read off
the slope -1/2 region around tau = 1 s, the floor read off the minimum, the local log-log
slopes, and the curve's own limit for each term (c_j^2 A_j(tau) <= sigma^2(tau)); and, for the
ADIS16405, the datasheet (noise density 0.05 deg/s/sqrt(Hz), in-run bias stability
0.007 deg/s). Numbers measured when this was written are in the comments.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from allan_independent import bound_ceiling, floor_fit
from recording_helpers import write_recording
from rigctl.analysis import allan as AA
from rigctl.analysis.allan import CHUNK_ROWS as CHUNK
from rigctl.solvers import allan_fit as F
from rigctl.solvers.noise_coefficients import resolved_values

FS = 100.0
TAU0 = 1.0 / FS
D2R = math.pi / 180.0
G0 = 9.80665
DEG_H = 180.0 / math.pi * 3600.0  # rad/s -> deg/h
#: ADIS16405 datasheet (typical): noise density 0.05 deg/s/sqrt(Hz) = 3.0 deg/sqrt(h); in-run
#: bias stability 0.007 deg/s = 25.2 deg/h (defined there as the minimum of the Allan curve)
ADIS_ARW_DEG_RT_H = 0.05 * 60.0
ADIS_BIAS_STAB_DEG_H = 0.007 * 3600.0
#: the IEEE 952 columns, written out here (not taken from the code under test)
B_FACTOR = math.sqrt(2.0 * math.log(2.0) / math.pi)  # 0.664


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"{path} not present (a commercial redistribution leaves it out: "
                    "CC BY-NC-SA 4.0, see its README)")
    return path


def _write(path: Path, gyro: np.ndarray, accel: np.ndarray | None = None) -> Path:
    return write_recording(path, FS, angular_rate=gyro,
                           **({"specific_force": accel} if accel is not None else {}))


def oadev(y: np.ndarray, ms: np.ndarray) -> np.ndarray:
    """Fully overlapping Allan deviation of a rate series at factors ms (plain numpy)."""
    x = np.concatenate(([0.0], np.cumsum(y - np.mean(y)))) * TAU0
    return np.array([math.sqrt(np.mean((x[2 * m:] - 2.0 * x[m:-m] + x[:-2 * m]) ** 2)
                               / (2.0 * (m * TAU0) ** 2)) for m in ms])


def slope(tau: np.ndarray, dev: np.ndarray, t0: float, t1: float) -> float:
    sel = (tau >= t0) & (tau <= t1)
    return float(np.polyfit(np.log(tau[sel]), np.log(dev[sel]), 1)[0])


def white_level(tau: np.ndarray, dev: np.ndarray) -> float:
    """N read off the slope -1/2 region around tau = 1 s: geometric mean of sigma sqrt(tau)."""
    sel = (tau >= 0.5) & (tau <= 2.0)
    return float(np.exp(np.mean(np.log(dev[sel] * np.sqrt(tau[sel])))))


def well_determined(edf: np.ndarray) -> np.ndarray:
    """Taus whose 95 % chi-square band is informative: hi95/lo95 = sqrt(chi2_0.975(nu) /
    chi2_0.025(nu)) <= 2, i.e. EDF nu >= 16.95 (scipy's chi-square, not the code under test)."""
    from scipy.stats import chi2

    nu = np.asarray(edf, dtype=float)
    return np.sqrt(chi2.ppf(0.975, nu) / chi2.ppf(0.025, nu)) <= 2.0


def limits(tau: np.ndarray, dev: np.ndarray) -> dict[str, float]:
    """The largest value of each term the curve allows (its sigma^2 part <= sigma^2)."""
    cols = {"Q": 3.0 / tau ** 2, "N": 1.0 / tau, "B": np.full(tau.shape, B_FACTOR ** 2),
            "K": tau / 3.0, "R": tau ** 2 / 2.0}
    return {t: float(np.sqrt(np.min(dev ** 2 / c))) for t, c in cols.items()}


@pytest.fixture(scope="module")
def adis(ref_data: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    d = _need(ref_data / "adis16405-static")
    gyro = np.loadtxt(d / "gyro_counts.txt.gz") * 0.05 * D2R
    accel = np.loadtxt(d / "accel_counts.txt.gz") * 0.00333 * G0
    rec = _write(tmp_path_factory.mktemp("adis") / "adis16405.h5", gyro, accel)
    # the excursions kept in the quiet stretches' fits (the ay stretch's hump is read below
    # with them in; the default leaves them out: benchmarks/allan_heldout.py judges that)
    res = AA.compute(str(rec), list(AA.AXES), excursions="report")
    return {"gyro": gyro, "accel": accel, "rec": rec, "res": res}


@pytest.fixture(scope="module")
def mtig(ref_data: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    d = _need(ref_data / "mtig-static-contaminated")
    g = np.loadtxt(d / "gyro_x_rad_s.txt.gz")
    rec = _write(tmp_path_factory.mktemp("mtig") / "mtig.h5", np.column_stack([g, g, g]))
    return {"gyro": g, "rec": rec, "res": AA.compute(str(rec), ["gx"])}


def _independent(y: np.ndarray, r: dict) -> tuple[np.ndarray, np.ndarray]:
    tau = np.asarray(r["tau_s"], dtype=float)
    return tau, oadev(y, np.asarray(r["m"]))


def _reported(r: dict) -> np.ndarray:
    return np.asarray(r[f"adev_{r['_si']}"], dtype=float)


def _ceiling(r: dict, sel: np.ndarray) -> np.ndarray:
    """The reported curve at the taus ``sel`` as a bound's ceiling (allan_independent.bound_ceiling:
    the curve itself where the fit needs a model error, else its simultaneous upper 95 % band)."""
    return bound_ceiling(_reported(r)[sel], np.asarray(r["edf"], float)[sel],
                         r["fit"]["check"]["model_error_rel"], F.MODEL_ERROR_HOLD)


def test_pipeline_curve_matches_plain_numpy(adis: dict, mtig: dict) -> None:
    """The deviations the fit sees are the overlapping ADEV: exact where the stride is 1, and
    where fast mode sums every (m/16 .. m/8)-th term its estimate keeps >= 90 % of the exact
    estimator's EDF (docs/allan.md), so it differs from the exact one by ~1/3 of the 68 %
    half-width (sd): never by more than the half-width. Measured: at most 0.56 of it."""
    cases = [(adis["gyro"][:, i], adis["res"]["axes"][a]) for i, a in enumerate(("gx", "gy", "gz"))]
    cases += [(adis["accel"][:, i], adis["res"]["axes"][a]) for i, a in enumerate(("ax", "ay", "az"))]
    cases.append((mtig["gyro"], mtig["res"]["axes"]["gx"]))
    for y, r in cases:
        tau, ind = _independent(y, r)
        dev = _reported(r)
        unit = r["_unit"]
        half68 = (np.asarray(r[f"hi68_{unit}"]) - np.asarray(r[f"lo68_{unit}"])) / 2.0 / np.asarray(r[f"adev_{unit}"])
        exact = np.asarray(r["stride"]) == 1
        np.testing.assert_allclose(dev[exact], ind[exact], rtol=1e-9)
        assert np.all(np.abs(dev / ind - 1.0) <= half68), np.max(np.abs(dev / ind - 1) / half68)


@pytest.mark.parametrize("axis", ["gx", "gy", "gz"])
def test_adis16405_gyro_floor_gives_an_estimate_of_b(adis: dict, axis: str) -> None:
    """The curve flattens between 30 and 300 s (independent slope |s| < 0.25 where white noise
    alone would give -0.5): B must be an estimate, not a bound, and the fitted total must
    follow the curve there. Measured: N 2.38 / 2.50 / 2.31 deg/sqrt(h) (read-off 2.46 / 2.58
    / 2.33), B 29.9 / 38.9 / 26.0 deg/h (min sigma / 0.664: 27.7 / 45.6 / 43.8; before this
    work the fit gave the bounds < 226 / < 1918 / < 1798 deg/h)."""
    i = "xyz".index(axis[1])
    r = adis["res"]["axes"][axis]
    tau, ind = _independent(adis["gyro"][:, i], r)
    assert abs(slope(tau, ind, 30.0, 300.0)) < 0.25  # the data: a floor
    co = r["fit"]["coefficients"]
    n_ind = white_level(tau, ind)
    n_fit = co.N.value
    assert co.N.resolved and abs(n_fit / n_ind - 1.0) < 0.10, (n_fit / n_ind)
    assert co.B.resolved, co.B
    b = co.B.value
    # within what the curve allows (its minimum over the taus with >= 20 averages, where the
    # deviation is known to better than ~25 %), and the fitted total follows the floor
    informative = np.asarray(r["m"]) * 20 <= r["n_samples"]
    assert B_FACTOR * b <= 1.25 * np.min(ind[informative])
    coeffs = resolved_values(r["fit"]["coefficients"])
    floor = (tau >= 30.0) & (tau <= 300.0)
    total = np.sqrt(F.model_avar(tau[floor], coeffs))
    assert np.all(np.abs(total / ind[floor] - 1.0) < 0.25), total / ind[floor]
    # the datasheet: noise density and in-run bias stability (the curve's minimum)
    assert 0.5 < n_fit * 60.0 / D2R / ADIS_ARW_DEG_RT_H < 1.5
    assert 0.5 < B_FACTOR * b * DEG_H / ADIS_BIAS_STAB_DEG_H < 2.0


def _tone_avar_numpy(m: np.ndarray, tau0: float, tones: list[dict]) -> np.ndarray:
    """Allan variance of sampled sinusoids a sin(2 pi f t): a^2 sin^4(pi f m tau0) /
    (m sin(pi f tau0))^2 each (written out here, not the code under test's)."""
    m = np.asarray(m, dtype=float)
    out = np.zeros(m.size)
    for t in tones:
        f, a = t["freq_hz"], t["amp_si"]
        out += a * a * np.sin(np.pi * f * m * tau0) ** 4 / (m * np.sin(np.pi * f * tau0)) ** 2
    return out


@pytest.mark.parametrize("axis", ["ax", "ay", "az"])
def test_adis16405_accel_floor_and_self_check(adis: dict, axis: str) -> None:
    """Accelerometers: a floor at 10-100 s (B an estimate within the curve's allowance), and a
    periodic component with a 1.77 s period (0.564 Hz, and its third harmonic at 1.69 Hz),
    which made the curve bump and dip around the fitted IEEE 952 total at 0.3-2 s. It is
    found before the fit (a numpy periodogram here finds the same frequency) and its Allan
    term carried in the model; the total with it then follows the curve, and wherever it does
    not (by more than 15 %) the self-check names the taus. The check still fails (the capture
    is not IEEE 952 plus tones alone)."""
    i = "xyz".index(axis[1])
    r = adis["res"]["axes"][axis]
    y = adis["accel"][:, i]
    tau, ind = _independent(y, r)
    assert abs(slope(tau, ind, 10.0, 100.0)) < 0.25
    fit = r["fit"]
    assert fit["coefficients"].B.resolved
    informative = np.asarray(r["m"]) * 20 <= r["n_samples"]
    assert B_FACTOR * fit["coefficients"].B.value <= 1.25 * np.min(ind[informative])
    check = fit["check"]
    # not IEEE 952 alone: the chi-square far beyond its 99 % point. (The model error it needed
    # was 0.18-0.27 of sigma^2 while the fit took the anti-aliasing filter's taus; with them
    # left out, az's is 0.008 -- its chi-square 406 on 37 dof, carried by 0.14-0.69 s, where
    # it was 32075: docs/allan.md, "The sensor's anti-aliasing filter"; that is a 10 Hz
    # vibration band, found and reported but not yet in the fit: "Vibration bands" there and
    # test_adis16405_accel_vibration_band_found_and_carries_az_chi_square below)
    assert check["p_value"] < 1e-6 and not check["ok"]
    # the periodic component: the strongest peak of a plain periodogram (2^15-sample Hann
    # segments averaged) between 0.1 and 10 Hz is the strongest tone found
    n_seg = 1 << 15
    segs = (y[: y.size // n_seg * n_seg] - y.mean()).reshape(-1, n_seg) * np.hanning(n_seg)
    psd = np.mean(np.abs(np.fft.rfft(segs, axis=1)) ** 2, axis=0)
    fr = np.fft.rfftfreq(n_seg, 0.01)
    band = (fr > 0.1) & (fr < 10.0)
    f_peak = fr[band][np.argmax(psd[band])]
    tones = r["tones"]["tones"]
    assert tones and abs(tones[0]["freq_hz"] - f_peak) < 2.0 / (n_seg * 0.01), (tones, f_peak)
    assert abs(tones[0]["freq_hz"] - 0.564) < 0.005
    # the independent read: the total (IEEE terms + the tones' term) against the curve; where
    # it is more than 15 % off, inside the band's informative taus, the check lists it
    coeffs = resolved_values(fit["coefficients"])
    ieee = F.model_avar(tau, coeffs)
    total = np.sqrt(ieee + _tone_avar_numpy(r["m"], 0.01, tones))
    sel = informative & (tau > 0.05) & (tau < 100.0)
    off = (np.abs(ind / total - 1.0) > 0.15) & sel
    named = np.zeros(tau.size, dtype=bool)
    for run in check["outside"]:
        named |= (tau >= run["tau_from_s"]) & (tau <= run["tau_to_s"])
    assert np.all(named[off]), tau[off & ~named]
    # and the tones' term is what the IEEE terms alone miss: without it the total is more
    # than 15 % off the curve somewhere in 0.3-2 s
    near = sel & (tau >= 0.3) & (tau <= 2.0)
    assert np.any(np.abs(ind[near] / np.sqrt(ieee[near]) - 1.0) > 0.15)


def _welch_numpy(y: np.ndarray, nper: int) -> tuple[np.ndarray, np.ndarray]:
    """One-sided Welch PSD written here: periodic Hann, segments of nper without overlap,
    each segment's mean removed, averaged."""
    k = y.size // nper
    seg = y[: k * nper].reshape(k, nper)
    seg = seg - seg.mean(axis=1, keepdims=True)
    w = 0.5 - 0.5 * np.cos(2.0 * np.pi * np.arange(nper) / nper)
    p = np.mean(np.abs(np.fft.rfft(seg * w, axis=1)) ** 2, axis=0) * 2.0 / (FS * np.sum(w * w))
    return np.fft.rfftfreq(nper, TAU0), p


def _band_numpy(y: np.ndarray, span: tuple[float, float], refs: tuple[tuple[float, float], ...]
                ) -> tuple[float, float, float, list[dict]]:
    """A band's read written here: the 2048-sample Welch PSD's excess over a straight line
    through its means over the two reference stretches ``refs`` (Hz, either side), over
    ``span``: (rms = sqrt(excess x bin width), the excess-weighted centre, the largest
    PSD / line, each bin's positive excess as a sinusoid {freq_hz, amp_si} of that power)."""
    f, p = _welch_numpy(y, 2048)
    (a0, a1), (b0, b1) = refs
    sa, sb = (f >= a0) & (f <= a1), (f >= b0) & (f <= b1)
    fa, fb, pa, pb = f[sa].mean(), f[sb].mean(), p[sa].mean(), p[sb].mean()
    line = pa + (pb - pa) * (f - fa) / (fb - fa)
    s = (f >= span[0]) & (f <= span[1])
    df = float(f[1] - f[0])
    exc = p[s] - line[s]
    pos = np.maximum(exc, 0.0)
    comps = [{"freq_hz": float(fj), "amp_si": math.sqrt(2.0 * e * df)} for fj, e in zip(f[s], pos) if e > 0]
    return (math.sqrt(float(exc.sum()) * df), float((f[s] * pos).sum() / pos.sum()),
            float(np.max(p[s] / line[s])), comps)


def test_adis16405_accel_vibration_band_found_and_carries_az_chi_square(adis: dict) -> None:
    """The ADIS16405 az's self-check (chi-square 406 on 37 dof with the filter's taus left
    out, carried by 0.14-0.69 s, the curve 1.001-1.011x the fitted total) is a vibration
    band: random power at ~9.4-12 Hz on all three accelerometers (1.5x the white level on az,
    2.3x ay, 3.5x ax; the z gyro has one at ~20 Hz, 15x; gx and gy none), too broad for a
    tone. Read here with numpy (Welch of 2048 samples, the excess over a line through 6-8.5
    and 13-16 Hz, summed over 9-12.5 Hz; measured az 0.449e-2 m/s^2 rms at 10.42 Hz, ay
    0.541e-2 at 10.25, ax 0.904e-2 at 10.24) and found by rigctl (tones.bands: az 0.378e-2
    at 10.26 Hz over 9.42-11.1 Hz; its read stops where the PSD first dips below the level,
    so it misses part of the tail to 12 Hz: 0.75-1.05x the read here). Its Allan term, from
    the numpy excess, carried in the fit (the tones' mechanism) takes az's chi-square from
    406 to 82 (measured): its positive term at m = 3-16 (up to 3 % of sigma^2 at 0.04 s)
    had hidden the low-pass filter's fading, so the filter's region ended at m = 8 (S rising
    0.03 then 0.13 of S(tau0) an octave) and its deficit was fitted; with the band carried the
    region reaches m = 64. rigctl does not carry the band yet (on ax and ay it changes more
    than the short taus: docs/allan.md, 'Vibration bands'): its warning says so, and the
    check still fails."""
    from rigctl.analysis.allan import band_warnings

    for i, axis in enumerate(("ax", "ay", "az")):
        r = adis["res"]["axes"][axis]
        rms, centre, peak, comps = _band_numpy(adis["accel"][:, i], (9.0, 12.5), ((6.0, 8.5), (13.0, 16.0)))
        assert peak > 1.3, (axis, peak)  # the data: a band, on every accelerometer
        bands = r["tones"]["bands"]
        assert len(bands) == 1, (axis, bands)
        b = bands[0]
        assert abs(b["freq_hz"] - centre) < 0.25 and 0.75 < b["rms_si"] / rms < 1.05, (axis, b, rms, centre)
        assert not any(abs(t["freq_hz"] - b["freq_hz"]) < 1.0 for t in r["tones"]["tones"])
        line = band_warnings(r)
        assert len(line) == 1 and "NOT in the fitted model" in line[0] and f"{b['freq_hz']:.4g} Hz" in line[0]
    for i, axis in enumerate(("gx", "gy")):  # no band on the x and y gyros, by either read
        assert _band_numpy(adis["gyro"][:, i], (9.0, 12.5), ((6.0, 8.5), (13.0, 16.0)))[2] < 1.2
        assert not adis["res"]["axes"][axis]["tones"]["bands"], axis
    # az: the band carries most of the chi-square (numpy's band through the fit's tones)
    r = adis["res"]["axes"]["az"]
    check = r["fit"]["check"]
    assert not check["ok"] and check["chi2"] > 5 * check["dof"]
    assert check["filter_excluded"]["m_to"] <= 8
    comps = _band_numpy(adis["accel"][:, 2], (9.0, 12.5), ((6.0, 8.5), (13.0, 16.0)))[3]
    tones = [{"freq_hz": t["freq_hz"], "amp_si": t["amp_si"]} for t in r["tones"]["tones"]]
    fit = F.fit_terms(np.asarray(r["tau_s"]), _reported(r), np.asarray(r["edf"]), "accel",
                      tau0=TAU0, n_phase=r["n_samples"] + 1, tones=tones + comps)
    c2 = fit["check"]
    assert c2["chi2"] < 0.3 * check["chi2"], (c2["chi2"], check["chi2"])
    assert c2["filter_excluded"]["m_to"] > 8
    # ... and N stays on the white level read off the spectrum (numpy, 2-8 Hz, one-sided
    # PSD / 2), within 2 %, as the reported fit's
    f, p = _welch_numpy(adis["accel"][:, 2], 2048)
    n_spec = math.sqrt(float(np.mean(p[(f >= 2.0) & (f <= 8.0)])) / 2.0)
    for co in (fit["coefficients"], r["fit"]["coefficients"]):
        assert abs(co.N.value / n_spec - 1.0) < 0.02, (co.N.value, n_spec)


def test_no_bound_above_what_the_curve_allows(adis: dict, mtig: dict) -> None:
    """Every term reported as a bound: at most the curve's own limit (B <= min sigma / 0.664,
    N <= min sigma sqrt(tau), K <= min sigma sqrt(3/tau), ...), read off the reported curve at
    its well-determined taus (EDF >= 16.95: the true sigma within 0.75 .. 1.5 x the measured
    one; the last taus of a capture, EDF 3-10, do not limit anything)."""
    results = list(adis["res"]["axes"].values()) + [mtig["res"]["axes"]["gx"]]
    n_bounds = 0
    for r in results:
        tau = np.asarray(r["tau_s"], dtype=float)
        sel = well_determined(r["edf"])
        assert sel.sum() >= 20
        lim = limits(tau[sel], _ceiling(r, sel))
        for t in r["fit"]["terms"]:
            c = getattr(r["fit"]["coefficients"], t)
            if not c.resolved:
                assert c.upper95 <= lim[t] * (1 + 1e-9), (t, c.upper95, lim[t])
                n_bounds += 1
    assert n_bounds >= 10


def test_mtig_no_floor_b_is_a_bound_and_the_bump_is_named(mtig: dict) -> None:
    """The MTi-G curve has no floor: a bump between ~5 and ~40 s, then slope -1/2 down to
    ~5 deg/h at 1000 s. B must come out as a bound at most min sigma / 0.664 (measured 8.1
    deg/h; the fit before this change put B at 30 deg/h, above the curve), N as an estimate
    within 10 % of the read-off, and the IEEE-only fit's self-check must name the bump, which
    the Gauss-Markov term then in the fit follows (within 15 % at 5-40 s; its check passes)."""
    r = mtig["res"]["axes"]["gx"]
    tau, ind = _independent(mtig["gyro"], r)
    informative = np.asarray(r["m"]) * 20 <= r["n_samples"]
    assert slope(tau, ind, 80.0, 400.0) < -0.35  # the data: still falling, no floor
    fit = r["fit"]
    b = fit["coefficients"].B
    assert not b.resolved
    sel = well_determined(r["edf"])
    assert b.upper95 * DEG_H <= np.min(_ceiling(r, sel)) / B_FACTOR * DEG_H * (1 + 1e-9)
    n_ind = white_level(tau, ind)
    assert abs(fit["coefficients"].N.value / n_ind - 1.0) < 0.10
    # the IEEE 952 terms alone (fit.ieee_only, kept since a Gauss-Markov term goes into the
    # fit where its test finds one) miss the bump and their check names it
    io_ = fit["ieee_only"]
    bump = [o for o in io_["check"]["outside"]
            if o["side"] == "data above the fit" and o["tau_from_s"] < 40.0 and o["tau_to_s"] > 5.0]
    assert not io_["check"]["ok"] and bump, io_["check"]["outside"]
    # independently: the curve stands > 15 % above their total somewhere in 5-40 s
    coeffs = resolved_values(io_["coefficients"])
    total = np.sqrt(F.model_avar(tau, coeffs))
    sel = (tau > 5.0) & (tau < 40.0) & informative
    assert np.max(ind[sel] / total[sel]) > 1.15
    # ... and the fit with the Gauss-Markov term (written out here) follows it within 15 %
    g = fit["coefficients"].gm[0]
    x = tau / g.tau_c_s
    with_gm = np.sqrt(F.model_avar(tau, resolved_values(fit["coefficients"]))
                      + g.sigma.value ** 2 * (2 * x - 3 + 4 * np.exp(-x) - np.exp(-2 * x)) / x ** 2)
    assert np.all(np.abs(ind[sel] / with_gm[sel] - 1.0) < 0.15), ind[sel] / with_gm[sel]
    assert fit["check"]["ok"]


def test_adis16405_quantization_read_from_the_samples(adis: dict) -> None:
    """The ADIS16405 outputs whole counts (0.05 deg/s, 3.33 mg): the pipeline reads the step
    from the samples and states the white noise its rounding adds, q sqrt(tau0/12), and its
    share of N^2 (measured: 0.13 % for gx, 4 % for az)."""
    for axis, step_si in (("gx", 0.05 * D2R), ("gy", 0.05 * D2R), ("gz", 0.05 * D2R),
                          ("ax", 0.00333 * G0), ("ay", 0.00333 * G0), ("az", 0.00333 * G0)):
        r = adis["res"]["axes"][axis]
        q = r["quantization"]
        assert q is not None and abs(q["step_si"] / step_si - 1.0) < 1e-9, (axis, q)
        nq = step_si * math.sqrt(TAU0 / 12.0)
        assert abs(q["white_N_si"] / nq - 1.0) < 1e-9
        n_fit = r["fit"]["coefficients"].N.value
        assert abs(q["share_of_N2"] - (nq / n_fit) ** 2) < 1e-12
        assert q["random_rounding"]  # several steps of noise per sample


def _spikes_numpy(y: np.ndarray, k: float = 10.0, window: int = 25) -> np.ndarray:
    """Samples more than k robust sd from the running median (plain numpy, edge-padded)."""
    h = window // 2
    pad = np.concatenate((np.full(h, y[0]), y, np.full(h, y[-1])))
    med = np.median(np.lib.stride_tricks.sliding_window_view(pad, window), axis=1)
    r = y - med
    sd = 1.4826 * np.median(np.abs(r - np.median(r)))
    return np.flatnonzero(np.abs(r) > k * sd)


def test_spikes_reported_and_optionally_excluded(adis: dict, mtig: dict, tmp_path: Path) -> None:
    """Spikes are found before the fit and reported, never silently folded in: the ADIS16405
    az holds 7 (15 sd), the MTi-G gyro 1730 (0.35 %, up to 148 sd). Excluded on request
    (--outliers exclude), the MTi-G's N^2 drops by the white variance the spikes carried
    (sum of their squared residuals x tau0 / n, computed here: 5.2e-8 rad^2/s; the fit's drop:
    6.0e-8, N 2.16 -> 1.99 deg/sqrt(h)), and the fit keeps its relation to the curve's own
    read-off (1.078x before, 1.073x after: the bump between 5 and 250 s, not the spikes)."""
    az = adis["res"]["axes"]["az"]["spikes"]
    ind = _spikes_numpy(adis["accel"][:200_000, 2])
    assert az["count"] >= ind.size > 0 and not az["excluded"]
    assert np.allclose(az["first_times_s"][:ind.size], ind[:len(az["first_times_s"])] * TAU0)
    for axis in ("gx", "gy", "gz"):
        assert adis["res"]["axes"][axis]["spikes"]["count"] == _spikes_numpy(
            adis["gyro"][:, "xyz".index(axis[1])]).size == 0
    g = mtig["gyro"]
    sp = mtig["res"]["axes"]["gx"]["spikes"]
    first = _spikes_numpy(g[:CHUNK])
    assert sp["count"] > 1000 and np.allclose(sp["first_times_s"], first[:10] * TAU0)
    res = AA.compute(str(mtig["rec"]), ["gx"], outliers="exclude")
    r = res["axes"]["gx"]
    assert r["spikes"]["excluded"] and r["spikes"]["count"] == sp["count"]
    # the cleaned series, independently: each spike replaced by its running median
    h = 12
    pad = np.concatenate((np.full(h, g[0]), g, np.full(h, g[-1])))
    idx = np.concatenate([_spikes_numpy(g[i:i + CHUNK]) + i for i in range(0, g.size, CHUNK)])
    clean = g.copy()
    clean[idx] = np.median(np.lib.stride_tricks.sliding_window_view(pad, 25)[idx], axis=1)
    spike_var = np.sum((g[idx] - clean[idx]) ** 2) * TAU0 / g.size
    tau, ind = _independent(clean, r)
    n_clean = white_level(tau, ind)
    n_dirty = white_level(*_independent(g, mtig["res"]["axes"]["gx"]))
    assert abs((n_dirty ** 2 - n_clean ** 2) / spike_var - 1.0) < 0.10  # the data: spikes = white
    n_fit = r["fit"]["coefficients"].N.value
    n_raw = mtig["res"]["axes"]["gx"]["fit"]["coefficients"].N.value
    assert 0.5 < (n_raw ** 2 - n_fit ** 2) / spike_var < 2.0
    assert abs((n_fit / n_clean) / (n_raw / n_dirty) - 1.0) < 0.02


def _flat_octave_numpy(tau: np.ndarray, dev: np.ndarray, t0: float, t1: float) -> float:
    """The largest |log-log slope| of the curve over any octave-long stretch inside [t0, t1]
    (plain numpy polyfit): small everywhere = flat throughout."""
    sel = (tau >= t0) & (tau <= t1)
    lt, ld = np.log(tau[sel]), np.log(dev[sel])
    worst = 0.0
    for a in range(lt.size):
        b = np.flatnonzero(lt - lt[a] >= math.log(2.0) * (1 - 1e-9))
        if b.size:
            worst = max(worst, abs(float(np.polyfit(lt[a:b[0] + 1], ld[a:b[0] + 1], 1)[0])))
    return worst


def test_adis16405_gz_octave_floor_gives_an_estimate(adis: dict) -> None:
    """Issue 15's held-out rehearsal: the ADIS16405 gz with --taus octave, whose curve is flat
    at 29-34 deg/h over 41-328 s (four octave taus, every octave-long stretch |slope| < 0.25
    here, the flatness the benchmark's floor read uses), came out as a bound (< 38.0 deg/h): B failed the 1.96 sd test once the model error
    (16-20 %) was added, and the floor exception covered only a B pressed against its limit.
    The curve needs B (N and K cannot make a flat octave), so B must be an estimate: within
    what the curve allows (min sigma / 0.664 over the well-determined taus, numpy), its 95 %
    interval reaching below that limit and holding B read by the floor fit written here
    (_np_b_fit: white noise read at 0.5-2 s, then B and K above it), and the datasheet's bias
    stability (25.2 deg/h) within 0.5-2x.

    The limit is an upper limit for B, not B's level: white noise alone (read here) is 28 % of
    sigma^2 at the floor's tau and K takes more, so a right interval need not reach it. It
    did before the intervals were built by Neyman's construction (26.5 [17.8, 52.0] deg/h,
    limit 43.8); now 28.3 [9.8, 39.5]. Simulated (the fitted N, B, K, 1e6 samples at 100 Hz,
    --taus octave, 76 seeds x 3 axes; /tmp scripts quoted in the commit of this change) the
    floor limit lies inside B's 95 % interval in 13 of 228 fits with nu read at the estimate
    and 9 of 228 with Neyman's, while the truth is inside in 202 and 203 of 228 (above it 26
    and 19, below 0 and 6). Measured: the floor fit here 23.8 [18.9, 27.9] deg/h."""
    res = AA.compute(str(adis["rec"]), ["gz"], taus="octave")
    r = res["axes"]["gz"]
    tau, ind = _independent(adis["gyro"][:, 2], r)
    assert _flat_octave_numpy(tau, ind, 40.0, 330.0) < 0.25  # the data: a flat floor
    sel = well_determined(r["edf"])
    lim = np.min(ind[sel]) / B_FACTOR
    t_floor = tau[sel][np.argmin(ind[sel])]
    # the data: the floor is not B alone -- white noise is a fifth or more of it there
    assert white_level(tau, ind) ** 2 / t_floor > 0.2 * np.min(ind[sel]) ** 2
    b = r["fit"]["coefficients"].B
    assert b.resolved, b
    assert b.value <= lim * (1 + 1e-6)
    assert b.ci95[0] <= lim, (b.ci95, lim)
    nb, nlo, nhi = _np_b_fit(adis["gyro"][:, 2], np.asarray(r["m"]), white=(0.5, 2.0))
    assert b.ci95[0] <= nb <= b.ci95[1], (b.ci95, (nb, nlo, nhi))
    assert 0.5 < B_FACTOR * b.value * DEG_H / ADIS_BIAS_STAB_DEG_H < 2.0


def test_mtig_small_gap_does_not_flip_b(mtig: dict) -> None:
    """Three dropped messages in a bag of the MTi-G took the EDF of the 369 s tau from 18.1
    to 16.0, below the 16.95 that makes a tau 'well-determined', and B flipped from a bound
    (< 12.0 deg/h) to an estimate 13.6 [9.4, 24.5]. The curve there still falls (slope
    about -1/2 from 160 to 820 s, numpy; no flat octave where B would be): B is a bound
    whichever side of the cut that tau's EDF lies, and the two bounds agree within 20 %."""
    r = mtig["res"]["axes"]["gx"]
    tau, ind = _independent(mtig["gyro"], r)
    assert slope(tau, ind, 160.0, 820.0) < -0.35
    assert _flat_octave_numpy(tau, ind, 150.0, 1000.0) > 0.25
    edf = np.asarray(r["edf"], dtype=float)
    k = int(np.argmin(np.abs(tau - 368.64)))
    assert well_determined(edf[k:k + 1])[0]
    bounds = []
    for factor in (1.0, 16.0 / float(edf[k])):
        e = edf.copy()
        e[k] *= factor
        fit = F.fit_terms(tau, _reported(r), e, "gyro", tau0=TAU0, n_phase=r["n_samples"] + 1)
        b = fit["coefficients"].B
        assert not b.resolved, (factor, b)
        bounds.append(b.upper95)
    assert abs(bounds[1] / bounds[0] - 1.0) < 0.2, bounds


def _pooled_oadev(parts: list[np.ndarray], ms: np.ndarray) -> np.ndarray:
    """Overlapping ADEV of gap-free stretches: every second difference inside a stretch is a
    term, a term touching the gap is skipped (Stable32), the terms pooled (plain numpy)."""
    mean = np.concatenate(parts).mean()
    xs = [np.concatenate(([0.0], np.cumsum(p - mean))) * TAU0 for p in parts]
    out = []
    for m in ms:
        ss, n = 0.0, 0
        for x in xs:
            if x.size > 2 * m:
                d = x[2 * m:] - 2.0 * x[m:-m] + x[:-2 * m]
                ss, n = ss + float(d @ d), n + d.size
        out.append(math.sqrt(ss / n / (2.0 * (m * TAU0) ** 2)))
    return np.array(out)


def test_mtig_bag_with_dropped_messages_octave_and_all_agree(mtig: dict, tmp_path: Path) -> None:
    """The MTi-G samples as a rosbag2 (mcap) with 3 messages dropped (one gap, skipped like
    Stable32), imported with `rigctl import`. Before, --taus all kept B as 19.9 [15.0, 29.7]
    deg/h -- its whole interval above the curve's min sigma / 0.664 = 13.66, the total 14.9
    deg/h at 327.7 s where the curve is 9.08 -- because the rule that drops a term the curve
    has come back down from judged N alone (6.867) against the pointwise 95 % band's lower
    edge (6.883) at that one tau; --taus octave bounded B at 13.66. The numpy read: the pooled
    curve still falls from 160 to 820 s (slope < -0.35, no floor), so B is a bound for both tau
    sets, at most min sigma / 0.664 over the well-determined taus, and N (within 10 % of the
    slope -1/2 read-off on the dense set) has overlapping 95 % intervals. Measured: B < 13.66
    both; N 2.13 [2.02, 2.25] (all) and 2.21 [2.02, 2.44] deg/sqrt(h) (octave). Not asserted,
    a finding: octave's N is 10.9 % above the read-off from its own two taus in 0.5-2 s
    (1.99 deg/sqrt(h)), which lies below its 95 % interval."""
    pytest.importorskip("rosbags")
    from rigctl import cli
    from rigctl.sim.imu_bag import write_imu_bag

    y = np.array([float(f"{v:.8g}") for v in mtig["gyro"]])
    keep = np.setdiff1d(np.arange(y.size), np.arange(200_000, 200_003))
    n = keep.size
    bag, rec = tmp_path / "mtig_bag", tmp_path / "mtig_bag.h5"
    write_imu_bag(bag, 1_600_000_000_000_000_000 + keep * 10_000_000,
                  np.column_stack([y[keep], np.zeros((n, 2))]), np.tile([0.0, 0.0, 9.81], (n, 1)),
                  topic="/imu", frame_id="imu", receive_delay_ns=2_000_000)
    assert cli.main(["import", str(bag), "-o", str(rec), "--force"]) == 0
    parts = [y[:200_000], y[200_003:]]
    fits = {}
    for taus in ("all", "octave"):
        r = AA.compute(str(rec), ["gx"], taus=taus)["axes"]["gx"]
        tau = np.asarray(r["tau_s"], dtype=float)
        ind = _pooled_oadev(parts, np.asarray(r["m"]))
        np.testing.assert_allclose(_reported(r)[np.asarray(r["stride"]) == 1],
                                   ind[np.asarray(r["stride"]) == 1], rtol=1e-6)
        assert slope(tau, ind, 160.0, 820.0) < -0.35  # the data: still falling, no floor
        sel = well_determined(r["edf"])
        lim = np.min(bound_ceiling(ind[sel], np.asarray(r["edf"])[sel],
                                   r["fit"]["check"]["model_error_rel"], F.MODEL_ERROR_HOLD)) / B_FACTOR
        b, nn = r["fit"]["coefficients"].B, r["fit"]["coefficients"].N
        assert not b.resolved, (taus, b.value * DEG_H, [v * DEG_H for v in b.ci95])
        assert b.upper95 <= lim * (1 + 1e-9), (taus, b.upper95 * DEG_H, lim * DEG_H)
        if taus == "all":  # octave has two taus in 0.5-2 s; see the docstring
            assert abs(nn.value / white_level(tau, ind) - 1.0) < 0.10
        fits[taus] = (b, nn)
    (ba, na), (bo, no) = fits["all"], fits["octave"]
    assert abs(ba.upper95 / bo.upper95 - 1.0) < 0.2, (ba.upper95 * DEG_H, bo.upper95 * DEG_H)
    assert na.ci95[0] <= no.ci95[1] and no.ci95[0] <= na.ci95[1], (na.ci95, no.ci95)


def _np_b_fit(y: np.ndarray, ms: np.ndarray,
              white: tuple[float, float] = (0.02, 0.2)) -> tuple[float, float, float]:
    """B (with a 95 % interval) by a fit written here: N read where white noise rules, the
    median of sigma sqrt(tau) over the informative taus in ``white`` (s; the accelerometers'
    0.02-0.2 s lies below their 0.564 Hz tone's taus); then B and K by weighted least squares
    on sigma^2 over the informative taus from 5 s on (var = 2 sigma^4 / EDF with the model's
    sigma^2, iterated, non-negative; EDF the smaller of flicker and white FM's NIST SP 1065
    forms; B's interval from that fit's covariance, the correlation across taus neglected)."""
    from scipy.stats import chi2

    dev, tau = oadev(y, ms), ms * TAU0
    n = float(len(y) + 1)
    ffm = np.array([2 * (n - 2) ** 2 / (2.3 * n - 4.9) if m == 1 else 5 * n * n / (4 * m * (n + 3 * m)) for m in ms])
    wfm = np.array([(3 * (n - 1) / (2 * m) - 2 * (n - 2) / n) * 4 * m * m / (4 * m * m + 5) for m in ms])
    nu = np.minimum(ffm, wfm)
    ok = np.sqrt(chi2.ppf(0.975, nu) / chi2.ppf(0.025, nu)) <= 2.0
    sh, fl = ok & (tau >= white[0]) & (tau <= white[1]), ok & (tau >= 5.0)
    n_white = float(np.median(dev[sh] * np.sqrt(tau[sh])))
    off = n_white ** 2 / tau[fl]
    return floor_fit(tau[fl], dev[fl], nu[fl], off)


@pytest.mark.parametrize("axis", ["ax", "ay"])
def test_adis16405_accel_quiet_stretch_b_against_a_fit_written_here(adis: dict, axis: str) -> None:
    """ADIS16405 ax and ay are not stationary by rigctl's own test (the Allan deviation at
    19-28 s differs across 8 windows of 1250 s, p 7e-6 / 3e-10), so the analysis also fits the
    quiet stretch that test names and reports it beside the whole record's terms (docs/allan.md,
    'Non-stationary records: the quiet stretch'). On that stretch, against _np_b_fit written
    here: rigctl's B within 20 % of it and their 95 % intervals overlap. Measured when written:
    ax t = 0-6250 s, rigctl 0.345 [0.320, 0.374] mg, here 0.352 [0.342, 0.361]; ay t =
    1250-6250 s, 0.252 [0.231, 0.277], here 0.242 [0.232, 0.252]."""
    r = adis["res"]["axes"][axis]
    q = r["quiet_stretch"]
    assert q["fitted"] and q["fraction"] >= 0.25, q
    a, b = q["samples"]
    assert 0 <= a < b <= r["n_samples"] and b - a < r["n_samples"]
    bq = q["fit"]["coefficients"].B
    assert bq.resolved, bq
    y = adis["accel"][:, "xyz".index(axis[1])]
    nb, nlo, nhi = _np_b_fit(y[a:b], np.asarray(q["m"]))
    assert 1 / 1.2 <= bq.value / nb <= 1.2, (bq.value, nb)
    assert bq.ci95[0] <= nhi and nlo <= bq.ci95[1], (bq.ci95, (nlo, nhi))
    # the whole record's B is still the whole record's (beside, not replaced)
    assert r["fit"]["coefficients"].B.value != bq.value


def test_adis16405_ay_quiet_stretch_hump_is_two_excursions_and_said_unexplained(adis: dict) -> None:
    """ADIS16405 ay's quiet stretch (rigctl's own choice, t = 1250-6250 s) still has a hump:
    read here in numpy, the deviation rises from 2.15e-3 m/s^2 at ~11 s to 4.09e-3 at ~200 s
    and falls to 3.7e-3 by 470 s. It is not a noise process of the sensor: two excursions of
    the accelerometers' bias inside the stretch, read off the 100-s means (t = 2100-2500 s:
    ay +2e-2 m/s^2, with ax, az and the three gyros moving at the same time; t = 5700-6000 s:
    ay -2e-2), carry it. Without them (the stretch less t = 2050-2650 and 5650-6100 s, terms
    touching a cut skipped) the curve is flat, 1.93-2.20e-3 from 10 to 300 s. No term rigctl
    fits follows it (its Gauss-Markov candidate: p = 0.053, best Tc 0.06 s, at the filter), so
    the stretch's self-check must name those taus as unexplained, in the JSON and the text,
    never as a named effect or a pass (it said "a correlated (Gauss-Markov) process ... stationary
    as far as the record shows" and the text printed only the chi-square's carrier at 0.01 s)."""
    from rigctl.analysis.allan_text import format_table

    r = adis["res"]["axes"]["ay"]
    q = r["quiet_stretch"]
    a, b = q["samples"]
    y = adis["accel"][:, 1]
    ms = np.asarray(q["m"])
    tau = ms * TAU0
    dev = oadev(y[a:b], ms)
    base = (tau >= 5.0) & (tau <= 20.0)
    hump = (tau >= 100.0) & (tau <= 250.0)
    assert dev[hump].max() / dev[base].min() > 1.6, dev  # measured 1.90
    # the same taus without the two excursions: the terms of each piece, pooled
    cuts = [(205_000, 265_000), (565_000, 610_000)]  # t = 2050-2650, 5650-6100 s of the record
    assert all(a < c0 < c1 < b for c0, c1 in cuts)
    pieces = [y[a:cuts[0][0]], y[cuts[0][1]:cuts[1][0]], y[cuts[1][1]:b]]
    pooled = []
    for m in ms[tau <= 300.0]:
        num = den = 0.0
        for p in pieces:
            x = np.concatenate(([0.0], np.cumsum(p - np.mean(y[a:b])))) * TAU0
            d = x[2 * m:] - 2.0 * x[m:-m] + x[:-2 * m]
            num, den = num + float(d @ d), den + d.size
        pooled.append(math.sqrt(num / den / (2.0 * (m * TAU0) ** 2)))
    pooled = np.array(pooled)
    t3 = tau[tau <= 300.0]
    flat = pooled[(t3 >= 10.0)]
    assert flat.max() / flat.min() < 1.2, pooled  # measured 1.14: no hump left
    # rigctl: the run over the hump is named, stationary by its test, and unexplained
    runs = [o for o in q["fit"]["check"]["outside"]
            if o["side"] == "data above the fit" and o["tau_from_s"] <= 150.0 <= o["tau_to_s"]]
    assert len(runs) == 1, q["fit"]["check"]["outside"]
    o = runs[0]
    assert o.get("unexplained") is True and "unexplained" in o["likely"], o
    assert not q["fit"].get("gm_term") and not q["fit"]["check"]["ok"]
    text = format_table("ay", r)
    line = next(s for s in text.splitlines()
                if s.startswith(f"warning: quiet stretch: tau {o['tau_from_s']:.3g}-"))
    assert "unexplained" in line, line
    # ... and the HTML report's quiet-stretch section names it under its table
    from rigctl.report.report_html import _quiet_stretch_html

    html = "".join(_quiet_stretch_html({"ay": r}))
    assert f"ay, quiet stretch: tau {o['tau_from_s']:.3g}-" in html and "unexplained" in html
