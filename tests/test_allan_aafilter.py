"""The sensor's anti-aliasing filter and the Allan fit (docs/allan.md, "The sensor's
anti-aliasing filter: its taus left out of the fit"; benchmarks/allan_aafilter.py).

White N 0.2 deg/sqrt(h) + flicker B 5 deg/h + random walk K 3 deg/h/sqrt(h) drawn at 1 kHz,
through a 2nd-order Butterworth at 40 Hz, every 10th sample kept: 5 minutes at 100 Hz, the
filter at 0.8 of the output's Nyquist. Before the filter's taus were left out, the self-check
failed on every such record (the curve 0.80-0.88x the fit at tau0) and N's 95 % interval held
the output's own white level on 8 of 20.

The expected N is computed here, independently of rigctl: the sampled output's white level,
N sqrt(sum_k R(k tau0) / R_unit) from the filter's impulse response (scipy.signal): every 10th
point is kept without averaging, so its PSD at f -> 0 keeps the aliased power.
"""
from __future__ import annotations

import html
import math

import numpy as np
import pytest
from scipy.signal import butter, lfilter

from allan_synth import synth_rate
from test_allan_check_bounds import FS, _adev, _edf
from rigctl.analysis.allan import excluded_sentences
from rigctl.report.report_html import _excluded_html
from rigctl.solvers import allan_fit as F

N_ARW = 0.2 / 60.0 * math.pi / 180.0  # rad/sqrt(s)
B_FLICKER = 5.0 / 3600.0 * math.pi / 180.0  # rad/s
K_RRW = 3.0 / 3600.0 / 60.0 * math.pi / 180.0  # rad/s/sqrt(s)
UP = 10
N_OUT = 30_000  # 5 min at FS


def _filter() -> tuple[np.ndarray, np.ndarray]:
    return butter(2, 40.0 / (FS * UP / 2.0))


def output_white_level() -> float:
    """The filtered, point-sampled output's own N (rad/sqrt(s)): the PSD at f -> 0 of every
    UP-th sample is N^2 (R(0) + 2 sum_k R(k UP)) UP / fs_in with R the impulse response's
    autocorrelation (unit DC gain: sum h = 1)."""
    b, a = _filter()
    h = lfilter(b, a, np.r_[1.0, np.zeros(4000)])
    acf = np.correlate(h, h, "full")[h.size - 1:]
    return N_ARW * math.sqrt((acf[0] + 2.0 * acf[UP::UP].sum()) * UP)


def _record(seed: int, filtered: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    if filtered:  # drawn at FS * UP, filtered, every UP-th sample kept
        b, a = _filter()
        y = lfilter(b, a, synth_rate(N_OUT * UP, FS * UP, N_ARW, B_FLICKER, K_RRW, seed))[::UP]
    else:  # the control: the same noise drawn at FS
        y = synth_rate(N_OUT, FS, N_ARW, B_FLICKER, K_RRW, seed)
    n_phase = y.size + 1
    ms = np.unique(np.round(np.logspace(0, np.log10((n_phase - 1) // 4), 40)).astype(int))
    return ms / FS, _adev(y, ms), _edf(ms.astype(float), n_phase), n_phase


@pytest.mark.parametrize("seed", [100, 101, 102])
def test_filtered_record_n_holds_the_outputs_level_and_the_check_passes(seed: int) -> None:
    tau, dev, edf, n_phase = _record(seed, filtered=True)
    n_out = output_white_level()
    # the data, read independently: sigma sqrt(tau) at tau0 is below the white level the
    # output keeps at m >= 8 (the filter's deficit), by more than the noise of either
    s = dev * np.sqrt(tau)
    m = np.round(tau * FS)
    assert s[0] < 0.92 * n_out and abs(np.median(s[(m >= 8) & (m <= 32)]) / n_out - 1) < 0.05
    fit = F.fit_terms(tau, dev, edf, "gyro", tau0=1.0 / FS, n_phase=n_phase)
    c, n = fit["check"], fit["coefficients"].N
    assert c["ok"], (c["chi2"], c["dof"], c.get("chi2_carried_by"))
    assert n.resolved and n.ci95[0] <= n_out <= n.ci95[1], (n.value / n_out, n.ci95, n_out)
    # the filter's taus are left out, said so, and still named by the check
    f = c["filter_excluded"]
    assert f is not None and f["tau_from_s"] == tau[0] and f["m_to"] >= 4
    assert fit["n_taus"] == tau.size - f["n_taus"]
    named = [o for o in c["outside"] if o["tau_to_s"] <= f["tau_to_s"]]
    assert named and all("data below" in o["side"] and "low-pass" in o["likely"] for o in named)
    text = " ".join(excluded_sentences(c))
    assert f"tau {tau[0]:.3g}-{f['tau_to_s']:.3g} s left out of the fit" in text
    assert "low-pass filter" in text
    # ... and the report's Allan section says the same
    page = " ".join(_excluded_html({"gx": {"fit": {"check": c}}}))
    assert "gx: " + html.escape(text.split(";")[0]) in page


@pytest.mark.parametrize("seed", [100, 101])
def test_unfiltered_record_leaves_every_tau_in_the_fit(seed: int) -> None:
    tau, dev, edf, n_phase = _record(seed, filtered=False)
    assert F.filter_region(tau, dev ** 2, edf, 1.0 / FS) is None
    fit = F.fit_terms(tau, dev, edf, "gyro", tau0=1.0 / FS, n_phase=n_phase)
    assert fit["check"]["filter_excluded"] is None and fit["n_taus"] == min(tau.size, 40)
    n = fit["coefficients"].N
    assert fit["check"]["ok"] and n.ci95[0] <= N_ARW <= n.ci95[1]
