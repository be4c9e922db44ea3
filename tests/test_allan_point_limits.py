"""Where the IEEE 952 model needs its own error, every term is held to the curve's own limit
(issue 15) -- for N and Q past a low-pass filter's region. The region is read off
S = sigma^2 tau; here on curves written out analytically (no sampling), each term's limit
computed here in numpy."""
from __future__ import annotations

import numpy as np

from rigctl.solvers import allan_fit as F

TAU0 = 0.01


def test_a_three_tap_filters_region_is_left_out_of_ns_limit() -> None:
    """White noise (N = 1) through taps (1/4, 1/2, 1/4): sigma^2 = 1/8 at m = 1 (the
    difference of neighbouring outputs is (-w0 - w1 + w2 + w3) / 4) and N^2 / tau - c / tau^2,
    c = 1.125 tau0, from m = 2 on: S rises by 0.31, 0.28, 0.14, 0.07, ... of N^2. Every
    tau below the last octave is the filter's (its deficit still fading), and N's hold is read
    from the last octave: within 4 % of the truth, where tau0 alone would give 0.35."""
    m = 2.0 ** np.arange(0, 11)
    tau = m * TAU0
    s2 = np.where(m == 1, 1.0 / (8.0 * TAU0), 1.0 / tau - 1.125 * TAU0 / tau ** 2)
    inf = np.ones(m.size, dtype=bool)
    region = F._filter_taus(tau, s2, inf, TAU0)
    assert region[:-1].all() and not region[-1]
    n_hold = np.sqrt(F._point_limits(tau, s2, inf, TAU0)[F.TERMS.index("N")])
    assert abs(n_hold - np.sqrt(1.0 - 1.125 / m[-1])) < 1e-12 and n_hold > 0.96
    assert np.sqrt(np.min(s2 * tau)) < 0.36


def test_a_correlated_process_from_tau0_has_no_filter_region() -> None:
    """White noise plus a flat floor (B) strong enough to show from tau0 on, S = N^2 +
    0.664^2 B^2 tau: S rises by more each octave -- no filter, N's hold is set at tau0 (the
    Astro Pi gyros' case: N 2.3x that limit before)."""
    m = 2.0 ** np.arange(0, 11)
    tau = m * TAU0
    s2 = 1.0 / tau + 0.664 ** 2 * 50.0 ** 2
    inf = np.ones(m.size, dtype=bool)
    assert not F._filter_taus(tau, s2, inf, TAU0).any()
    lim = F._point_limits(tau, s2, inf, TAU0)
    assert abs(lim[F.TERMS.index("N")] / (s2[0] * tau[0]) - 1.0) < 1e-12
    # the other terms: min sigma^2 / A_j(tau) over the taus, written out
    assert abs(lim[F.TERMS.index("B")] / (np.min(s2) / 0.664 ** 2) - 1.0) < 1e-3
    assert abs(lim[F.TERMS.index("K")] / np.min(s2 * 3.0 / tau) - 1.0) < 1e-12
    assert abs(lim[F.TERMS.index("R")] / np.min(s2 * 2.0 / tau ** 2) - 1.0) < 1e-12
    assert abs(lim[F.TERMS.index("Q")] / np.min(s2 * tau ** 2 / 3.0) - 1.0) < 1e-12
