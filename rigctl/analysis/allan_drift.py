"""Slow features of a static capture that are not IEEE 952 noise, for the Allan pipeline
(:mod:`rigctl.analysis.allan`): a start transient (warm-up) and a drift that follows the
recorded temperature. The statistics are :mod:`rigctl.solvers.allan_drift`'s; this module reads
an axis' block means from the streamed record (the decimated phase the noise identification
keeps), puts the results in the axis' result (``warmup``, ``temperature``), names them in the
fit's self-check where they explain the taus outside the band, and words them.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from .. import display_units as DU
from ..solvers import allan_drift as D
from ..solvers import allan_fit as F
from ..solvers import allan_gm as GM
from ..solvers import allan_stationarity as ST
from ..solvers import allan_tones as TN
from ..solvers import noise_coefficients as NC

G0 = 9.80665
#: display unit of a level (the deviation's field unit) and of a rate of change per K
LEVEL_UNITS = {"gyro": ("deg/h", 180.0 / math.pi * 3600.0), "accel": ("mg", 1000.0 / G0)}

#: what to do with a start transient found before the fit: report it, or cut the record's
#: start (the longest trim over the axes) and analyse the rest
WARMUP_MODES = ("report", "exclude")


def block_means(phase: np.ndarray, step_s: float) -> tuple[np.ndarray, float]:
    """Block means of the rate from the phase sampled every ``step_s`` (the stream's
    decimated copy), averaged down to at most D.MAX_BLOCKS blocks: (means, block length s)."""
    x = np.asarray(phase, dtype=float)
    k = max(1, -(-(x.size - 1) // D.MAX_BLOCKS))
    xs = x[::k]  # every k-th phase point: the block means are their differences
    return np.diff(xs) / (k * step_s), k * step_s


def start_transient(ybar: np.ndarray, block_s: float, tau: np.ndarray, dev: np.ndarray,
                    record_s: float, sensor: str) -> dict[str, Any]:
    """The start-transient test and, when it finds one, the exponential's fit, its Allan
    deviation at the curve's taus (``adev_si``, SI) and the cut that would leave less than a
    tenth of the curve (``trim_s``); amplitude also in the deviation's field unit."""
    test = D.start_transient_test(ybar, block_s)
    out: dict[str, Any] = {"detected": test["detected"], "p_value": test["p_value"],
                           "alpha": test["alpha"], "test": test}
    if not test["detected"]:
        return out
    fit = D.fit_start_transient(ybar, block_s, test["best_T_s"], record_s)
    if "skipped" in fit:
        out["fit"] = fit
        return out
    unit, fac = LEVEL_UNITS[sensor]
    amp_hi = max(abs(fit["amp_ci95"][0]), abs(fit["amp_ci95"][1]))
    tau_hi = fit["tau_ci95"][1]
    trim = D.trim_for(amp_hi, tau_hi, tau, dev, record_s)
    w2 = D.transient_avar(tau, fit["amp"], fit["tau_s"], record_s)
    share = w2 / np.maximum(np.asarray(dev, dtype=float) ** 2, 1e-300)
    k = int(np.argmax(share))
    out.update({"fit": fit, "amp_si": fit["amp"], "tau_s": fit["tau_s"],
                "tau_ci95_s": fit["tau_ci95"], "amp_ci95_si": fit["amp_ci95"],
                f"amp_{unit}": fit["amp"] * fac,
                f"amp_ci95_{unit}": [v * fac for v in fit["amp_ci95"]], "unit": unit,
                "trim_s": float(trim), "adev_si": np.sqrt(w2), "share": share,
                "max_share": float(share[k]), "max_share_tau_s": float(np.asarray(tau)[k])})
    return out


def name_in_check(check: dict, tau: np.ndarray, share: np.ndarray, why: str, key: str,
                  why_below: str | None = None) -> int:
    """Put the runs of taus outside the band down to a feature (``key``) that is not IEEE 952
    noise: a run where the feature's Allan variance is at least D.NAME_SHARE of the curve's at
    some tau of it gets ``why``; with ``why_below``, a run of data below the fit at taus past
    the feature's largest share (when that share reaches D.NAME_SHARE) gets it: the fit's
    long-tau terms (K, B) took the feature and overshoot the curve there. The earlier reason
    is kept in ``likely_before``. Returns the runs renamed."""
    tau = np.asarray(tau, dtype=float)
    share = np.asarray(share, dtype=float)
    k = int(np.argmax(share)) if share.size else 0
    peak_ok = share.size and float(share[k]) >= D.NAME_SHARE
    renamed = 0
    for o in check.get("outside") or []:
        sel = (tau >= o["tau_from_s"] * (1 - 1e-12)) & (tau <= o["tau_to_s"] * (1 + 1e-12))
        # a named cause stays, but for "nonstationary" (name_bumps): a warm-up or the
        # temperature says what the disturbance is
        if not sel.any() or o.get("cause") not in (None, "nonstationary"):
            continue
        if float(np.max(share[sel])) >= D.NAME_SHARE:
            reason = why
        elif (why_below and peak_ok and o["side"] == "data below the fit"
              and o["tau_from_s"] >= float(tau[k])):
            reason = why_below
        else:
            continue
        if "likely_before" not in o:
            o["likely_before"] = o["likely"]
        elif o.get("cause") == "nonstationary":
            o["likely_nonstationary"] = o["likely"]
        o["likely"] = reason
        o["cause"] = key
        renamed += 1
    return renamed


def _fit_dev(fit: dict, tau: float) -> float:
    """The fitted total the self-check compares at ``tau``: the resolved IEEE 952 terms
    (:func:`rigctl.solvers.noise_coefficients.resolved_values`), the Gauss-Markov term where
    the fit has one, plus the tones' Allan term."""
    s2 = float(F.fitted_avar(fit, np.array([tau]))[0])
    tn = fit.get("tones") or {}
    if tn.get("terms"):
        t0 = float(tn["tau0_s"])
        s2 += float(TN.tones_avar(t0, np.array([max(1.0, round(tau / t0))]), tn["terms"])[0])
    return math.sqrt(max(s2, 0.0))


def _test_run(o: dict, ybar: np.ndarray, block_s: float, fit: dict | None) -> dict:
    """The stationarity test of one run: at its worst tau and, given the fit, also at its
    first, middle and last tau (those with at least two windows; each at ST.ALPHA / the
    number tested, Bonferroni). A bump's worst tau can lie far from the hump when the fit
    itself is pulled by it (a strong Gauss-Markov process: the fit's N follows its 1/tau tail).
    Returns the result at the worst tau when it is significant or the only one, else at the
    tau of the smallest p."""
    worst = float(o["worst_tau_s"])
    taus = [worst]
    if fit is not None:
        a, b = float(o["tau_from_s"]), float(o["tau_to_s"])
        for t in (a, math.sqrt(a * b), b):
            if all(abs(t / u - 1.0) > 0.1 for u in taus):
                taus.append(t)
    first = [ST.bump_stationarity(ybar, block_s, t) for t in taus]
    # the tau the block means give (a multiple of their length) must lie in the run: the
    # ADIS16405 gz's one-tau run at 0.07 s, block means 0.02 s long, would be tested at 0.08 s
    lo, hi = float(o["tau_from_s"]) * 0.95, float(o["tau_to_s"]) * 1.05
    ok = [t for t, st in zip(taus, first) if st["tested"] and lo <= st["tau_s"] <= hi]
    if not ok:
        st = first[0]
        if st["tested"]:
            st = {"tested": False, "tau_s": st["tau_s"], "alpha": st["alpha"],
                  "skipped": f"the block means ({block_s:g} s) give no tau inside the run"}
        return st
    alpha = ST.ALPHA / len(ok)
    res = [ST.bump_stationarity(ybar, block_s, t, alpha=alpha) for t in ok]
    for st in res:
        st["taus_tested"] = len(ok)
    if ok[0] == worst and not res[0]["stationary"]:
        return res[0]
    return min(res, key=lambda st: st["p_value"])


def name_bumps(check: dict, ybar: np.ndarray, block_s: float, tau0: float | None = None,
               fit: dict | None = None) -> int:
    """Test each run of taus the self-check calls a bump (data above the fit, not at either
    end, no cause named yet) for stationarity (:func:`rigctl.solvers.allan_stationarity.
    bump_stationarity` on the block means, at the run's worst tau, and given the ``fit``
    (its ``coefficients`` and ``tones``) at its ends and middle too, :func:`_test_run`; the
    result in the run's ``stationarity``). A bump that is not stationary, and absent from the
    median window (within DEPARTURE_REL of the fitted total there), gets :func:`bump_reason`
    (``cause`` "nonstationary", the earlier reason in ``likely_before``); otherwise the run
    keeps its reason with the test's outcome appended. Returns the runs renamed."""
    renamed = 0
    for o in check.get("outside") or []:
        if (o.get("cause") or o.get("side") != "data above the fit"
                or not str(o.get("likely", "")).startswith("a bump")):
            continue
        st = _test_run(o, ybar, block_s, fit)
        o["stationarity"] = st
        if not st["tested"]:
            continue
        many = (f" each of {st['taus_tested']} taus of the run tested"
                if st.get("taus_tested", 1) > 1 else "")
        if st["stationary"]:
            o["likely"] = (f"{o['likely']}; stationary as far as the record shows: its Allan "
                           f"variance at {st['tau_s']:.3g} s does not differ across "
                           f"{st['windows']} windows of {st['window_s']:.0f} s beyond chance "
                           f"(Bartlett p = {st['p_value']:.2g}, alpha {st['alpha']:.2g}{many})")
            continue
        if tau0:  # the quiet stretch in samples of the range analysed (for --segments, and
            # for the quiet-stretch fit: rigctl.analysis.allan_quiet)
            st["quiet_samples"] = [int(round(st["quiet"][0] / tau0)),
                                   int(round(st["quiet"][1] / tau0))]
        # the bump is the excursions' only when the typical (median) window has none of it:
        # its deviation within the self-check's DEPARTURE_REL of the fitted total (with
        # thousands of averages per window a 2 % change of level is significant, and
        # explains no bump of 12 %)
        if fit is not None:
            fit_at = _fit_dev(fit, st["tau_s"])
        else:  # the run's own ratio, at its worst tau (the only one tested without the fit)
            fit_at = st["adev_whole_si"] / float(o["data_over_fit"])
        st["median_window_over_fit"] = st["adev_median_window_si"] / max(fit_at, 1e-300)
        if st["median_window_over_fit"] > 1.0 + F.DEPARTURE_REL:
            o["likely"] = (f"{o['likely']}; its level varies along the record (Bartlett p = "
                           f"{st['p_value']:.2g}, alpha {st['alpha']:.2g}{many}), but the median window of "
                           f"{st['window_s']:.0f} s has it too ("
                           + (f"x{st['median_window_over_fit']:.2f} the fit"
                              if st["median_window_over_fit"] < F.NO_TOTAL_RATIO
                              else "the fit has no total there") + f" at {st['tau_s']:.3g} s)")
            continue
        o["likely_before"] = o["likely"]
        o["likely"] = bump_reason(st)
        o["cause"] = "nonstationary"
        renamed += 1
    return renamed


def bump_reason(st: dict[str, Any]) -> str:
    """The self-check's reason for a bump whose Allan variance is not the same across the
    record (a disturbance in part of it)."""
    r = np.sqrt(np.asarray(st["ratio_to_median"], dtype=float))
    loud = st["loud"] or [max(((a, b, v) for a, b, v in zip(
        np.arange(st["windows"]) * st["window_s"], np.arange(1, st["windows"] + 1) * st["window_s"],
        st["ratio_to_median"])), key=lambda w: w[2])]
    where = ", ".join(f"t = {a:.0f}-{b:.0f} s (x{math.sqrt(v):.2g})" for a, b, v in loud)
    q = st["quiet"]
    return (f"not stationary noise: the Allan deviation at {st['tau_s']:.3g} s differs across "
            f"the record's {st['windows']} windows of {st['window_s']:.0f} s beyond chance "
            f"(x{r.min():.2g} to x{r.max():.2g} of the median window's; Bartlett p = "
            f"{st['p_value']:.2g}, alpha {st['alpha']:.2g}"
            + (f" each of {st['taus_tested']} taus of the run tested" if st.get("taus_tested", 1) > 1 else "")
            + "; the median window within "
            f"{100 * F.DEPARTURE_REL:.0f} % of the fit); it comes from {where}: a disturbance "
            "in part of the record (excursions of the rate, a noise level that changes), not "
            "a term of a stationary noise model; to see the noise without it, analyse a quiet "
            f"stretch (rigctl import --segments): the longest whose windows agree is t = "
            f"{q[0]:.0f}-{q[1]:.0f} s (x{q[2]:.2g} the record's deviation there)"
            + (f", samples {st['quiet_samples'][0]}-{st['quiet_samples'][1]} of the range "
               "analysed" if "quiet_samples" in st else ""))


def warmup_reason(w: dict[str, Any]) -> str:
    """The self-check's reason for the taus a start transient explains."""
    unit = w["unit"]
    return (f"a warm-up transient at the start of the record (the mean settles by "
            f"{w[f'amp_{unit}']:.3g} {unit} with a time constant of {w['tau_s']:.3g} s; its "
            f"own Allan deviation is up to {100 * math.sqrt(w['max_share']):.0f} % of the "
            f"curve's), not a term of the noise: trim the first {w['trim_s']:.0f} s "
            "(--warmup exclude)")


def warmup_reason_below(w: dict[str, Any]) -> str:
    """The self-check's reason for data below the fit past the transient's taus."""
    unit = w["unit"]
    return (f"the fitted K and B take the warm-up transient at the start of the record "
            f"({w[f'amp_{unit}']:.3g} {unit}, time constant {w['tau_s']:.3g} s; its Allan "
            f"deviation is up to {100 * math.sqrt(w['max_share']):.0f} % of the curve at "
            f"{w['max_share_tau_s']:.3g} s) and overshoot the curve here: trim the first "
            f"{w['trim_s']:.0f} s (--warmup exclude)")


def warmup_sentences(r: dict[str, Any]) -> list[str]:
    """Warnings on an axis' start transient ([] if none was found): the one found (before
    the cut, with --warmup exclude) and, after a cut, any still found."""
    ex = r.get("warmup_excluded")
    w = (ex or {}).get("before") or r.get("warmup") or {}
    out = []
    if w.get("detected") and "tau_s" in w:
        unit = w["unit"]
        lo, hi = w[f"amp_ci95_{unit}"]
        tl, th = w["tau_ci95_s"]
        head = (f"start transient (warm-up): the mean settles exponentially by "
                f"{w[f'amp_{unit}']:.3g} {unit} [{lo:.3g}, {hi:.3g}] with a time constant of "
                f"{w['tau_s']:.3g} s [{tl:.3g}, {th:.3g}] (95 %; test p = {w['p_value']:.2g} "
                f"against the record's own later differences, alpha {w['alpha']:g}); its Allan "
                f"deviation reaches {100 * math.sqrt(w['max_share']):.0f} % of the curve (at "
                f"{w['max_share_tau_s']:.3g} s)")
        how = w["fit"].get("interval_from", "")
        if "Newey-West" in how or "overlapping" in how:
            head += f" -- intervals from {how}"
        if ex:
            out.append(f"{head}: the first {ex['trim_s']:.0f} s were cut before the deviations "
                       f"(--warmup exclude; with them: {ex['summary_before']})")
        else:
            out.append(f"{head}: it is in the curve and the fit (K and B take it); to leave it "
                       f"out: --warmup exclude (cuts the first {w['trim_s']:.0f} s)")
    now = r.get("warmup") or {}
    if ex and now.get("detected") and "tau_s" in now:
        unit = now["unit"]
        out.append(f"after the cut a start transient is still found ({now[f'amp_{unit}']:.3g} "
                   f"{unit}, time constant {now['tau_s']:.3g} s, p = {now['p_value']:.2g})")
    return out


# ------------------------------------------------------------------ temperature
#: what to do with a drift that follows the recorded temperature: report it, or subtract the
#: fitted temperature term from the samples and analyse again
TEMPERATURE_MODES = ("report", "remove")
#: the slow part of the signal: the record in about this many block means
TEMP_BLOCKS = 128
#: the temperature is named when the regression's p is below this (per axis)
TEMP_ALPHA = 1e-3
#: per-sample units of a temperature coefficient, per sensor (field unit per K)
COEF_UNITS = {"gyro": ("deg/h/K", 180.0 / math.pi * 3600.0), "accel": ("mg/K", 1000.0 / G0)}


def read_temperature_blocks(path: str, s0: int, rows_per_block: int, n_blocks: int
                            ) -> np.ndarray | None:
    """Means of /imu/temperature over the same row blocks as an axis' block means (rows
    s0 + i rows_per_block ...), read in pieces; None without a usable temperature (absent,
    not one value per IMU row, fewer than 90 % finite, or constant)."""
    import h5py

    with h5py.File(path, "r") as f:
        ds = f.get("imu/temperature")
        if ds is None or ds.ndim != 1 or ds.shape[0] < s0 + n_blocks * rows_per_block:
            return None
        # a look at 256 rows first: a constant or missing temperature (the recorder writes
        # the column for every IMU, a day at 2 kHz is 0.7 GB of it) is not read through
        probe = np.asarray(ds[np.unique(np.linspace(s0, s0 + n_blocks * rows_per_block - 1,
                                                    256).astype(np.int64))], dtype=float)
        fin = np.isfinite(probe)
        if fin.mean() < 0.9 or np.ptp(probe[fin]) <= 0:
            return None
        out = np.empty(n_blocks)
        step = max(1, (1 << 20) // rows_per_block)
        for i in range(0, n_blocks, step):
            j = min(n_blocks, i + step)
            v = np.asarray(ds[s0 + i * rows_per_block: s0 + j * rows_per_block], dtype=float)
            out[i:j] = v.reshape(j - i, rows_per_block).mean(axis=1)
    fin = np.isfinite(out)
    if fin.mean() < 0.9 or np.ptp(out[fin]) <= 0:
        return None
    return out


def temperature_check(ybar: np.ndarray, tbar: np.ndarray, block_s: float, rows_per_block: int,
                      tau: np.ndarray, dev: np.ndarray, sensor: str) -> dict[str, Any]:
    """The regression of the slow part of the signal (about TEMP_BLOCKS block means) on the
    temperature (:func:`rigctl.solvers.allan_drift.temperature_regression`), the temperature
    term's Allan deviation at the curve's taus (the coarse temperature interpolated to the
    fine blocks, times the coefficient) and its share of the curve; ``correction``: the term
    at the coarse blocks' centre rows (relative to the range's first row), for
    --temperature remove."""
    k = max(1, ybar.size // TEMP_BLOCKS)
    yc, tc = D.aggregate(ybar, k), D.aggregate(tbar, k)
    reg = D.temperature_regression(yc, tc)
    unit, fac = COEF_UNITS[sensor]
    out: dict[str, Any] = {"found": False, "alpha": TEMP_ALPHA, "block_s": k * block_s,
                           "blocks": int(yc.size), **reg}
    if "skipped" in reg:
        return out
    out.update({"found": bool(reg["p_value"] < TEMP_ALPHA), "coef_field": reg["coef"] * fac,
                "coef_unit": unit,
                "coef_ci95_field": [v * fac for v in reg["coef_ci95"]]})
    fin = np.isfinite(tc)
    centres = (np.arange(tc.size) + 0.5) * k
    t_fine = np.interp(np.arange(tbar.size) + 0.5, centres[fin], tc[fin])
    t_ref = float(np.mean(tc[fin]))
    term = reg["coef"] * (t_fine - t_ref)
    adev = D.series_adev(term, block_s, tau)
    share = np.nan_to_num(adev ** 2 / np.maximum(np.asarray(dev, dtype=float) ** 2, 1e-300))
    i = int(np.argmax(share))
    out.update({"temp_ref_degC": t_ref, "adev_si": adev, "share": share,
                "max_share": float(share[i]), "max_share_tau_s": float(np.asarray(tau)[i]),
                "correction": {"rows": centres[fin] * rows_per_block,
                               "values": reg["coef"] * (tc[fin] - t_ref)}})
    return out


def correction_at(corr: dict, first: int, n: int) -> np.ndarray:
    """The correction of rows first .. first + n - 1 (relative to the range's first row):
    the term at the block centres, interpolated linearly (held beyond the first and last)."""
    rows = np.arange(first, first + n, dtype=float)
    return np.interp(rows, np.asarray(corr["rows"], float), np.asarray(corr["values"], float))


def temperature_reason(t: dict[str, Any]) -> str:
    lo, hi = t["coef_ci95_field"]
    return (f"the recorded temperature: the slow part of the signal follows it by "
            f"{t['coef_field']:.3g} {t['coef_unit']} [{lo:.3g}, {hi:.3g}] (95 %), and "
            f"that term's own Allan deviation is up to {100 * math.sqrt(t['max_share']):.0f} % of "
            f"the curve's (at {t['max_share_tau_s']:.3g} s), not a term of the noise: "
            "--temperature remove takes it out")


def temperature_step(path: str, s0: int, axes: dict[str, dict]) -> None:
    """Each analysed axis' ``temperature`` (:func:`temperature_check`) when the recording
    has a usable /imu/temperature (else ``{"found": False, "skipped": ...}``), and the fit's
    self-check runs it explains named (after the warm-up's, which go first); the block means
    the analysis kept (``_blocks``) are dropped."""
    read: dict[tuple[int, int], np.ndarray | None] = {}  # one read per block layout
    for r in axes.values():
        blk = r.pop("_blocks", None)
        if blk is None:
            continue
        key = (blk["rows_per_block"], blk["ybar"].size)
        if key not in read:
            read[key] = read_temperature_blocks(path, s0, *key)
        tbar = read[key]
        if tbar is None:
            r["temperature"] = {"found": False, "skipped": "no usable /imu/temperature"}
            continue
        dev = np.asarray(r[f"adev_{r['_si']}"], dtype=float)
        t = temperature_check(blk["ybar"], tbar, blk["block_s"], blk["rows_per_block"],
                              r["tau_s"], dev, r["sensor"])
        r["temperature"] = t
        if t["found"]:
            name_in_check(r["fit"]["check"], r["tau_s"], t["share"], temperature_reason(t),
                          "temperature")


def temperature_sentences(r: dict[str, Any]) -> tuple[list[str], list[str]]:
    """(warnings, notes) on an axis' drift against the recorded temperature."""
    rm = r.get("temperature_removed")
    t = (rm or {}).get("before") or r.get("temperature") or {}
    if "coef" not in t:
        return [], []
    lo, hi = t["coef_ci95_field"]
    what = (f"{t['coef_field']:.3g} {t['coef_unit']} [{lo:.3g}, {hi:.3g}] (95 %; "
            f"differences of {t['blocks']} block means of {t['block_s']:.4g} s on the recorded "
            f"temperature, span {t['temp_span_K']:.3g} K, p = {t['p_value']:.2g})")
    if not t["found"]:
        return [], [f"no drift with the recorded temperature: {what}"]
    head = (f"the slow part of the signal follows the recorded temperature: {what}; that "
            f"term's Allan deviation reaches {100 * math.sqrt(t['max_share']):.0f} % of the "
            f"curve (at {t['max_share_tau_s']:.3g} s)")
    if rm:
        return [f"{head}: subtracted from the samples before the deviations (--temperature "
                f"remove; with it: {rm['summary_before']})"], []
    return [f"{head}: it is in the curve and the fit; to take it out: --temperature remove"], []


def plot_extras(r: dict[str, Any]) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(label, tau, Allan deviation in SI) of the warm-up transient and the temperature term
    found on an axis (as analysed: after a cut or a removal, what is left of them), for the
    plot; [] if none."""
    out = []
    w = r.get("warmup") or {}
    if w.get("detected") and "adev_si" in w:
        out.append((f"warm-up transient ({w['tau_s']:.3g} s)", r["tau_s"], w["adev_si"]))
    t = r.get("temperature") or {}
    if t.get("found") and "adev_si" in t:
        out.append((f"temperature term ({t['coef_field']:.3g} {t['coef_unit']})", r["tau_s"],
                    t["adev_si"]))
    return out


def gauss_markov(fit: dict, tau: np.ndarray, dev: np.ndarray, edf: np.ndarray, tau0: float,
                 n_phase: int, sensor: str, stretch_samples: np.ndarray | None = None
                 ) -> dict | None:
    """A first-order Gauss-Markov candidate for the stationary bumps of the self-check
    (:func:`rigctl.solvers.allan_gm.gm_candidate`: its likelihood-ratio test against the IEEE
    952 terms alone), run only when a run of taus the check calls a bump was tested stationary
    by :func:`name_bumps` (never for one it calls nonstationary). The result goes into
    ``fit["gauss_markov"]`` (sigma_GM also in the deviation's field unit,
    :data:`rigctl.display_units.NOISE_UNITS`: B's); where the test finds the process and its
    hump (1.89 Tc) lies within a factor 4 of the run, the run's reason names it as a candidate
    with the error before and after. The fitted total and the self-check are those of the IEEE
    952 terms: the candidate is not in them. Every stationary bump the candidate does not
    explain is said to be unexplained (:func:`name_unexplained`, :func:`gm_not_found_reason`).

    Also run when the check passed (so lists no bump) but the fit reports B as an estimate
    (a floor): a hump of a Gauss-Markov process can pass the check taken as flicker, B then
    inflated (5-minute records with a bump of 4 B at Tc 2 s: B 2.7-3.1x its truth, the check
    passed; docs/allan.md, "Detection limits"). The self-check is a goodness-of-fit test and
    does not compare the nested models; the candidate's likelihood ratio does. Such a result
    is kept (``unprompted`` True) only when the process is found and no run of taus the check
    lists lies within a factor 4 of its hump (a warm-up, a non-stationary bump or an excursion
    there is not a stationary process); else it is dropped and the result is None, as before.
    There the test runs only after its cheap screen (``gm_candidate(screen=True)``) gives
    p < GM_SCREEN_P: its cost is the Gauss-Markov kernel's, per Tc and sampling."""
    runs = stationary_bumps(fit.get("check") or {})
    b = getattr(fit.get("coefficients"), "B", None)
    # only where the IEEE terms' self-check passed: the case this is for (a hump passed as
    # flicker) and what the added term's sentence says. A failed check names its own causes: on
    # an emulated power-on record the check failed on the warm-up, the candidate found a 2 s
    # process (p 4.7e-4) and the refit took the 270 s transient as a GM term of Tc 359 s
    # (test_allan_warmup)
    unprompted = (not runs and bool((fit.get("check") or {}).get("ok"))
                  and bool(b is not None and b.resolved))
    if not runs and not unprompted:
        return None
    tn = fit.get("tones") or {}
    if unprompted and not (GM.gm_candidate(
            tau, dev, edf, tau0, n_phase, tones=tn.get("terms") or None,
            stretch_samples=stretch_samples, screen=True).get("p_value", 1.0) < GM.GM_SCREEN_P):
        return None  # the cheap screen first (no Gauss-Markov kernel, the coarse Tc grid)
    gm = GM.gm_candidate(tau, dev, edf, tau0, n_phase,
                         tones=tn.get("terms") or None, stretch_samples=stretch_samples)
    if unprompted:
        peak = GM.GM_PEAK * gm.get("tc_s", math.nan)
        near = [o for o in (fit.get("check") or {}).get("outside") or []
                if float(o["tau_from_s"]) / 4.0 <= peak <= 4.0 * float(o["tau_to_s"])]
        if not gm.get("detected") or near:
            return None
        gm["unprompted"] = True
        gm["ieee_b_field"] = b.value * DU.NOISE_UNITS[sensor]["B"][1]
    unit, fac = DU.NOISE_UNITS[sensor]["B"]
    if gm.get("tested"):
        gm["sigma_gm_unit"] = unit
        gm[f"sigma_gm_{DU.slug(unit)}"] = gm["sigma_gm_si"] * fac
        gm[f"sigma_gm_ci95_{DU.slug(unit)}"] = [v * fac for v in gm["sigma_gm_ci95_si"]]
    gm["runs_stationary"] = len(runs)
    fit["gauss_markov"] = gm
    if gm.get("detected"):
        peak = GM.GM_PEAK * gm["tc_s"]
        for o in runs:
            if not (float(o["tau_from_s"]) / 4.0 <= peak <= 4.0 * float(o["tau_to_s"])):
                continue
            o["gauss_markov"] = True
            o["likely"] = f"{o['likely']}; {gm_reason(gm)}"
    name_unexplained(fit.get("check") or {}, gm_not_found_reason(gm))
    return gm


def stationary_bumps(check: dict) -> list[dict]:
    """The runs of taus the self-check calls a bump (data above the fit, no cause named) that
    :func:`name_bumps` tested stationary."""
    return [o for o in check.get("outside") or []
            if o.get("cause") is None and o.get("side") == "data above the fit"
            and str(o.get("likely", "")).startswith("a bump")
            and (o.get("stationarity") or {}).get("stationary")]


def name_unexplained(check: dict, why: str) -> int:
    """Say of each stationary bump that no term of the fit follows (none marked
    ``gauss_markov``) that it is unexplained: ``unexplained`` True and the sentence appended
    to its reason, so that a failed self-check never reads as a named effect. Returns the
    runs marked."""
    n = 0
    for o in stationary_bumps(check):
        if o.get("gauss_markov") or o.get("unexplained"):
            continue
        o["unexplained"] = True
        o["likely"] = f"{o['likely']}; unexplained: {why}"
        n += 1
    return n


def gm_left_reason(fit: dict) -> str:
    """Why a stationary bump left beside a fitted Gauss-Markov term is unexplained."""
    t = fit.get("gm_term") or {}
    tc = t.get("tc_s", math.nan)
    return (f"the fit's Gauss-Markov term (Tc {tc:.3g} s, its hump at {GM.GM_PEAK * tc:.3g} s) "
            "does not follow it, and no IEEE 952 term within the curve's limits does")


def gm_not_found_reason(gm: dict) -> str:
    """Why the Gauss-Markov candidate does not explain a stationary bump, in words: not
    tested, not significant, or significant with its hump (1.89 Tc) elsewhere on the curve."""
    if not gm.get("tested"):
        return (f"no Gauss-Markov candidate could be tested ({gm.get('skipped', 'not tested')}), "
                "and no IEEE 952 term within the curve's limits follows it")
    where = (f"best Tc {gm['tc_s']:.3g} s, its hump at {GM.GM_PEAK * gm['tc_s']:.3g} s"
             if math.isfinite(gm.get("tc_s", math.nan)) else "")
    if not gm.get("detected"):
        return (f"no first-order Gauss-Markov term is significant beside the IEEE 952 terms "
                f"(likelihood ratio p = {gm['p_value']:.2g}, alpha {gm['alpha']:.3g}"
                + (f"; {where}" if where else "") + "), and no IEEE 952 term within the "
                "curve's limits follows it")
    return (f"the Gauss-Markov process the candidate finds ({where}) is not at this run, and no "
            "IEEE 952 term within the curve's limits follows it")


def gm_added(gm: dict | None, fit: dict) -> bool:
    """Does the Gauss-Markov term go into the joint fit? When (and only when) the candidate's
    likelihood-ratio test found it (``detected``) and its hump lies at a stationary bump the
    self-check names (:func:`gauss_markov` marked the run), or, where the check names none,
    the candidate was run beside a B estimate and found it there (``unprompted``)."""
    return bool(gm and gm.get("detected") and (gm.get("unprompted") or any(
        o.get("gauss_markov") for o in (fit.get("check") or {}).get("outside") or [])))


def refit_with_gm(fit: dict, gm: dict, sensor: str, refit: Any) -> dict:
    """The joint fit again with the Gauss-Markov term in the model (``refit(gm_spec)``:
    :func:`rigctl.solvers.allan_fit.fit_terms` with ``gm``), Tc searched over the candidate's
    range. The new fit keeps the candidate (``gauss_markov``, ``in_fit`` True) and what the IEEE
    952 terms alone gave (``ieee_only``: their coefficients and self-check); its ``gm_term``
    gains sigma_GM in the deviation's field unit (B's) and the candidate's test, for the
    warning (:func:`gm_added_sentence`)."""
    new = refit({"tc_grid_s": gm["tc_grid_s"]})
    unit, fac = DU.NOISE_UNITS[sensor]["B"]
    t = new.get("gm_term") or {}
    if t:
        t["sigma_unit"] = unit
        t[f"sigma_{DU.slug(unit)}"] = t["sigma_si"] * fac
        t[f"sigma_ci95_{DU.slug(unit)}"] = [v * fac for v in t["sigma_ci95_si"]]
        t["test"] = {k: gm.get(k) for k in ("p_value", "alpha", "statistic", "n_looks")}
    gm = dict(gm)
    gm["in_fit"] = bool(t)
    new["gauss_markov"] = gm
    ch = fit.get("check") or {}
    for o in ch.get("outside") or []:  # the candidate's sentence: now in the fit
        if o.get("gauss_markov") and new.get("gm_term"):
            o["likely"] = str(o["likely"]).replace("a candidate, not in the fitted total",
                                                   "added to the joint fit")
    new["ieee_only"] = {"coefficients": fit["coefficients"], "terms": fit.get("terms"),
                        "check": {k: ch.get(k) for k in (
                            "ok", "chi2", "dof", "p_value", "model_error_rel", "n_outside",
                            "n_informative", "n_outside_band", "outside")}}
    return new


def gm_added_sentence(fit: dict) -> str:
    """The warning that a Gauss-Markov term is in the fit, and why ('' when none)."""
    t = fit.get("gm_term")
    if not t:
        return ""
    unit = t["sigma_unit"]
    s, (s_lo, s_hi) = t[f"sigma_{DU.slug(unit)}"], t[f"sigma_ci95_{DU.slug(unit)}"]
    gm = fit.get("gauss_markov") or {}
    io = (fit.get("ieee_only") or {}).get("check") or {}
    ch = fit.get("check") or {}
    test = t.get("test") or {}
    before = (f"; chi2/dof of the reported model {io['chi2']:.4g}/{io['dof']} without it -> "
              f"{ch['chi2']:.4g}/{ch['dof']} with it" if io.get("chi2") is not None
              and ch.get("chi2") is not None else "")
    what = (f"sigma_GM {s:.3g} {unit} [{s_lo:.3g}, {s_hi:.3g}]" if t.get("resolved")
            else f"sigma_GM < {s_hi:.3g} {unit} (the joint fit does not resolve it)")
    return (f"a first-order Gauss-Markov term was added to the fit: Tc {t['tc_s']:.3g} s "
            f"{tc_interval(t)}, {what} (95 %), "
            + (f"because the likelihood-ratio test against the IEEE 952 terms alone finds the "
               f"process, which their fit took as flicker (B {gm['ieee_b_field']:.3g} "
               f"{gm['sigma_gm_unit']} without the term; its self-check passed) (p = "
               if gm.get("unprompted") else
               "because the curve has a stationary bump the IEEE 952 terms cannot follow and the "
               "likelihood-ratio test against them finds the process (p = ")
            + f"{test.get('p_value', math.nan):.2g}, alpha {test.get('alpha', math.nan):.3g}, "
            f"{test.get('n_looks', math.nan):.2g} looks over Tc; the candidate's Tc "
            f"{gm.get('tc_s', math.nan):.3g} s){before}; the terms, the fitted total and the "
            "self-check include it"
            + ("; held at the curve's own limit" if t.get("held_at_curve_limit") else ""))


def tc_interval(t: dict[str, Any], digits: int = 3) -> str:
    """Tc's 95 % interval of a Gauss-Markov result (the fit's ``gm_term`` or the candidate's
    ``gauss_markov``) as "[lo, hi]", an end whose profile set reaches the end of the Tc range
    searched written open ("[<lo, hi]", "[lo, >hi]": the range's end, not the data's;
    :func:`rigctl.solvers.noise_coefficients.tc_interval_text`)."""
    return NC.tc_interval_text(t["tc_ci95_s"], t.get("tc_ci95_open"), digits)


def gm_reason(gm: dict) -> str:
    """The candidate's sentence in the self-check's reason for a stationary bump."""
    unit = gm["sigma_gm_unit"]
    s, (s_lo, s_hi) = gm[f"sigma_gm_{DU.slug(unit)}"], gm[f"sigma_gm_ci95_{DU.slug(unit)}"]
    rb, ra = gm["ratio_before"], gm["ratio_after"]
    return (f"a Gauss-Markov process with Tc ~ {gm['tc_s']:.3g} s {tc_interval(gm)} "
            f"and sigma_GM {s:.3g} {unit} [{s_lo:.3g}, {s_hi:.3g}] (95 %) fits the bump: "
            f"chi2/dof {gm['chi2_before']:.1f}/{gm['dof_before']} -> "
            f"{gm['chi2_after']:.1f}/{gm['dof_after']}, data/total {rb[0]:.2f}-{rb[1]:.2f} -> "
            f"{ra[0]:.2f}-{ra[1]:.2f} over taus {gm['tau_range_s'][0]:.3g}-"
            f"{gm['tau_range_s'][1]:.3g} s (likelihood ratio against the IEEE 952 terms alone, "
            f"p = {gm['p_value']:.2g}, alpha {gm['alpha']:.3g}; a candidate, not in the fitted "
            "total)")
