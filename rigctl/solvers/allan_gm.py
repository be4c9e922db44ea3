"""A first-order Gauss-Markov (exponentially correlated) process beside the IEEE 952 terms:
a named candidate for a stationary bump the IEEE 952 fit cannot follow (pure functions).

The rate y(t) with autocovariance sigma_GM^2 exp(-|t| / Tc) has the Allan variance (IEEE Std
952-1997 annex C; e.g. Jerath et al., "Bridging the gap between sensor noise modeling and sensor
characterization", 2018)::

    sigma^2(tau) = sigma_GM^2 (Tc / tau)^2 (2 tau / Tc - 3 + 4 e^(-tau/Tc) - e^(-2 tau/Tc))

a hump near tau = 1.89 Tc: for tau << Tc a rate random walk (K^2 = 2 sigma_GM^2 / Tc), for
tau >> Tc a white noise (N^2 = 2 sigma_GM^2 Tc). Linear in sigma_GM^2 at a fixed Tc.

:func:`gm_candidate` asks whether the curve needs it: a likelihood-ratio test of sigma_GM^2 = 0
against sigma_GM^2 > 0 beside every IEEE 952 shape, built like the fit's B presence test
(:func:`rigctl.solvers.allan_fit.b_presence_test`: taus of at least B_TEST_M_MIN samples, Q's
1/tau^2 column with a free sign for a low-pass, non-negative generalized least squares with the
covariance of the sigma^2 estimates, a relative model error where even the alternative leaves
scatter beyond the statistics), with two differences:

* the covariance of the estimates is that of the fitted N, B, K and Gauss-Markov terms with
  their cross terms, at each Tc tried (allan_cov's Gauss-Markov kernel,
  :func:`rigctl.solvers.allan_cov.gm_term_covariances`), scaled tau by tau to the whole
  alternative (the signed Q and the ramp take the same correlations, as in the fit);
* Tc is not defined under the null (Davies' problem): the statistic is the largest over a grid
  of Tc (4 per octave on the lattice 2^(i/4) s, refined to 2^(j/32) s around the best, so
  that axes and records of one sampling share the kernel's cache; the hump's peak 1.89 Tc
  inside the well-determined curve), and its
  boundary p-value (chi-bar-square, chi2.sf(stat, 1) / 2) is multiplied by the number of
  independent looks, one per factor GM_LOOK_SPAN of Tc (Bonferroni). The false-add rate this
  gives is measured, not assumed (tests/test_allan_gm.py, benchmarks/allan_gm.py).

A hump whose best Tc lies at either end of the grid is not a candidate (there the process is a
white noise or a random walk, which N and K already are).
"""
from __future__ import annotations

import math

import numpy as np
from .distributions import chi2

from . import allan_cov as C
from . import allan_fit as F
from .allan_fit import solve_triangular  # scipy's, without its wrapper's cost
from . import allan_tones as TN
from .allan_stream import blas_single_thread

#: design level: the chance that a curve of IEEE 952 noise (white + random walk; N + B + K) is
#: given a Gauss-Markov candidate (the B presence test's level)
GM_TEST_ALPHA = 0.025
#: one independent look at the data per this factor of Tc (the hump spans ~1.5 decades)
GM_LOOK_SPAN = 4.0
#: Tc grid: this many points per octave
GM_GRID_PER_OCTAVE = 4
#: the hump's peak (1.89 Tc) must lie this factor inside the well-determined taus
GM_PEAK = 1.89
#: the screen's p-value (gm_candidate(screen=True)) below which the test is run where no bump
#: prompts it: on 80 records with a bump (5 min, sigma 2 and 4 B, Tc 2 s) every one the test
#: found had a screen p <= 0.023; 6 of 40 records without one pass the screen
GM_SCREEN_P = 0.2


#: the Allan variance of the process (defined in allan_fit, whose joint fit carries the term)
gm_avar = F.gm_avar


def _interval(p: float, sd: float, conf: float) -> tuple[float, float]:
    """Satterthwaite chi-square interval of a variance p with sd (the fit's form), as sqrt."""
    if not (p > 0 and sd > 0):
        return (0.0, math.inf)
    return F._chi2_ci(p, 2.0 * p * p / (sd * sd), conf)


def gm_candidate(tau: np.ndarray, adev: np.ndarray, edf: np.ndarray, tau0: float,
                 n_phase: int, tones: list[dict] | None = None, max_taus: int = 40,
                 iterations: int = 3, stretch_samples: np.ndarray | None = None,
                 screen: bool = False) -> dict:
    """:func:`_gm_candidate` with BLAS single-threaded (40 x 40 systems: threads only cost).
    A curve no positive IEEE 952 term describes (a recording of a moving table: the deviation
    rises from 0.01 to 1 s and falls again) leaves the weighted least squares singular (every
    term 0, the model's variance underflows): then no test, said in ``skipped``."""
    with blas_single_thread():
        try:
            return _gm_candidate(tau, adev, edf, tau0, n_phase, tones, max_taus, iterations,
                                 stretch_samples, screen)
        except np.linalg.LinAlgError as exc:
            return {"tested": False, "detected": False, "p_value": math.nan,
                    "alpha": GM_TEST_ALPHA,
                    "skipped": f"no test: the weighted least squares is singular ({exc}); the "
                               "IEEE 952 terms do not describe this curve"}


def _gm_candidate(tau: np.ndarray, adev: np.ndarray, edf: np.ndarray, tau0: float,
                  n_phase: int, tones: list[dict] | None = None, max_taus: int = 40,
                  iterations: int = 3, stretch_samples: np.ndarray | None = None,
                  screen: bool = False) -> dict:
    """Does a first-order Gauss-Markov term fit the curve beyond the IEEE 952 terms? (see the
    module docstring). ``stretch_samples``: the gap-free stretches' lengths when the deviations
    pool them (gaps skipped): the covariance is then the pooled estimator's
    (:func:`rigctl.solvers.allan_cov.gapped_term_covariances` with the Gauss-Markov kernel). ``tones``: the tones the fit subtracts (their Allan term is taken off
    here too). Returns {"tested", "detected", "p_value", "statistic", "alpha", "n_looks",
    "tc_s", "tc_ci95_s", "sigma_gm_si", "sigma_gm_ci95_si", "chi2_before", "chi2_after",
    "dof_before", "dof_after", "ratio_before", "ratio_after" (data / fitted total over the
    well-determined taus tested: min, max), "n_informative", "n_outside95_before",
    "n_outside95_after" (of those taus, outside their pointwise 95 % band), "tau_range_s",
    "model_error_rel"}; "before" is the IEEE 952 terms alone refitted on the same taus with the
    same covariance, not the main fit's reported total.

    ``screen``: a cheap first look (``screen`` True in the result): the covariance of the IEEE
    terms alone scaled tau by tau to the whole model (no Gauss-Markov kernel: the IEEE terms'
    matrices are cached per sampling, the kernel's are computed per Tc) and the coarse Tc grid
    only; its p-value is for deciding whether to run the test, not a result."""
    out: dict = {"tested": False, "detected": False, "p_value": math.nan,
                 "alpha": GM_TEST_ALPHA}
    tau = np.asarray(tau, dtype=float)
    s2 = np.asarray(adev, dtype=float) ** 2
    e = np.asarray(edf, dtype=float)
    ms = np.maximum(1, np.round(tau / tau0))
    if tones:
        s2 = s2 - TN.tones_avar(tau0, ms, tones)
    lo = s2 * e / chi2.ppf(0.975, np.maximum(e, 1e-9))
    hi = s2 * e / chi2.ppf(0.025, np.maximum(e, 1e-9))
    ok = np.isfinite(s2) & (s2 > 0) & np.isfinite(e) & (e > 0) & (ms >= F.B_TEST_M_MIN)
    inf = ok & (np.sqrt(hi) <= F.INFORMATIVE_RATIO * np.sqrt(lo))
    if np.count_nonzero(inf) < 8:
        out["skipped"] = "fewer than 8 well-determined taus past the filter's"
        return out
    sel = np.flatnonzero(ok)
    sel = sel[F._thin(sel.size, max_taus)]
    t, y, ee = tau[sel], s2[sel], e[sel]
    t_inf = tau[inf]
    tc_lo, tc_hi = 2.0 * t_inf[0] / GM_PEAK, t_inf[-1] / (2.0 * GM_PEAK)
    if tc_hi <= 2.0 * tc_lo:
        out["skipped"] = "the well-determined curve is too short for a hump inside it"
        return out
    i_lo = int(math.ceil(math.log2(tc_lo) * GM_GRID_PER_OCTAVE))
    i_hi = int(math.floor(math.log2(tc_hi) * GM_GRID_PER_OCTAVE))
    grid = 2.0 ** (np.arange(i_lo, i_hi + 1) / GM_GRID_PER_OCTAVE)
    n_looks = max(1.0, math.log(tc_hi / tc_lo) / math.log(GM_LOOK_SPAN))
    ms_t = np.round(t / tau0).astype(np.int64)
    gapped = stretch_samples is not None and len(stretch_samples) > 1
    a0 = F.design_matrix(t)
    lower = np.array([-np.inf, 0.0, 0.0, 0.0, 0.0, 0.0])

    def solve(a: np.ndarray, lw: np.ndarray, bw: np.ndarray | None = None
              ) -> tuple[np.ndarray, float, np.ndarray]:
        aw = solve_triangular(lw, a, lower=True)
        if bw is None:
            bw = solve_triangular(lw, y, lower=True)
        sc = np.linalg.norm(aw, axis=0)
        sc[sc == 0] = 1.0
        k = a.shape[1]
        q = F.bvls(aw / sc, bw, lower[:k], np.full(k, np.inf)) / sc
        r = bw - aw @ q
        return q, float(r @ r), aw

    def whiten_at(a: np.ndarray, q: np.ndarray, eps: float, ct: dict) -> np.ndarray:
        """The covariance of the N, B, K and GM terms at q (the GM kernel's, with the cross
        terms), scaled per tau to the whole model; the diagonal 2 mod^2 / edf if it is not
        positive; plus the model error (eps mod)^2."""
        p = np.maximum(q, 0.0)
        # the terms the covariance holds (the screen's: the IEEE terms', whose correlations
        # then stand for the Gauss-Markov term's too, scaled to the whole model)
        held = [1, 2, 3] if screen else [1, 2, 3, 5]
        noisy = np.maximum(a[:, held] @ p[held], 1e-300)
        mod = np.maximum(a @ q, 1e-300)
        cov = C.combine(ct, {"N": p[1], "B": p[2], "K": p[3], "G": p[5]})
        g = mod / noisy
        with np.errstate(over="ignore", invalid="ignore"):
            cov = cov * np.outer(g, g)
        if not np.all(np.isfinite(cov)) or not np.all(np.diag(cov) > 0):
            cov = np.diag(2.0 * mod ** 2 / ee)
        if eps > 0:
            cov = cov + np.diag((eps * mod) ** 2)
        return F._whiten(cov)

    # at(tc, eps) is a pure function of its arguments: each pair is computed once (the model
    # error's search ends at a value it evaluated at the best Tc, which the grid then repeats)
    done: dict[tuple[float, float], dict] = {}

    def at(tc: float, eps: float) -> dict:
        key = (float(tc), float(eps))
        if key not in done:
            done[key] = _at(tc, eps)
        return done[key]

    def _at(tc: float, eps: float) -> dict:
        a = np.column_stack((a0, gm_avar(t, 1.0, tc)))
        tk = None if screen else tc
        ct = (C.gapped_term_covariances(tau0, ms_t, np.asarray(stretch_samples), tk)
              if gapped else C.term_covariances(tau0, ms_t, int(n_phase), tk))
        lw = F._whiten_diag(2.0 * y ** 2 / ee + (eps * y) ** 2)
        for _ in range(iterations):
            q, _, _ = solve(a, lw)
            lw = whiten_at(a, q, eps, ct)
        bw = solve_triangular(lw, y, lower=True)
        q1, c1, aw = solve(a, lw, bw)
        # the null fit (IEEE terms alone, same whitener): read only at the Tc the test and
        # the report use (null()), so solved there only
        return {"tc": tc, "q1": q1, "c1": c1, "aw": aw, "a": a, "lw": lw, "bw": bw}

    def null(r: dict) -> dict:
        """``r`` with the null fit's q0, c0 (solved once, on r's whitener)."""
        if "c0" not in r:
            r["q0"], r["c0"], _ = solve(a0, r["lw"], r["bw"])
        return r

    runs = [at(tc, 0.0) for tc in grid]
    best = min(runs, key=lambda r: r["c1"])
    dof1 = max(1, t.size - int(np.count_nonzero(best["q1"])))
    eps = 0.0
    if chi2.sf(best["c1"], dof1) < F.MODEL_ERROR_P:
        # the alternative does not describe the taus to their statistical precision either:
        # its relative model error, as in the B test (reduced chi-square 1 at the best Tc)
        eps = F._unit_reduced_chi2_eps(lambda x: at(best["tc"], x)["c1"] / dof1)
        runs = [at(tc, eps) for tc in grid]
        best = min(runs, key=lambda r: r["c1"])
    over = max(1.0, best["c1"] / dof1)
    # the best Tc (least alternative chi-square: the profile over Tc) and the statistic there
    i = int(np.argmin([r["c1"] for r in runs]))
    interior = 0 < i < len(runs) - 1
    # ... refined 8x around the coarse grid's best (the profile is a few grid steps wide)
    j0 = 8 * (i_lo + max(i - 2, 0))
    j1 = 8 * (i_lo + min(i + 2, grid.size - 1))
    fine = 2.0 ** (np.arange(j0, j1 + 1) / (8 * GM_GRID_PER_OCTAVE)) if not screen else grid
    runs = sorted(runs + [at(tc, eps) for tc in fine if not np.any(np.isclose(tc, grid))],
                  key=lambda r: r["tc"])
    i = int(np.argmin([r["c1"] for r in runs]))
    # the test: its statistic at the best Tc of the range searched (the looks counted there)
    tested = null(runs[i])
    stat = max(tested["c0"] - tested["c1"], 0.0) / over
    p = min(1.0, n_looks * 0.5 * float(chi2.sf(stat, 1))) if stat > 0 else 1.0
    # Tc and its 95 % interval: the profile of the alternative's chi-square (scaled by the
    # overdispersion), bracketed by the next evaluated Tc, by the fit's rule
    # (allan_fit.tc_profile_interval); where its set reaches the range's lowest Tc the profile
    # is continued below it on the lattice, down to the first tau tested / GM_BELOW_FIRST_TAU
    # (allan_fit.extend_tc_profile_below, the fit's own continuation), and an end still at the
    # last Tc evaluated is open (the range's, not the data's). Before, the interval was cut
    # at the range: simulated Tc 0.04 s (range from 0.042 s) inside it 0 of 11 times.
    if not screen:
        lattice = 8 * GM_GRID_PER_OCTAVE
        below: dict[float, dict] = {}

        def at_below(tc: float) -> tuple[float, float]:
            r = at(2.0 ** (round(math.log2(tc) * lattice) / lattice), eps)  # the kernel's lattice
            below[tc] = r
            return r["c1"], r["c1"]

        floor = 2.0 ** (math.floor(math.log2(t[0] / F.GM_BELOW_FIRST_TAU) * GM_GRID_PER_OCTAVE)
                        / GM_GRID_PER_OCTAVE)
        tcs0 = np.array([r["tc"] for r in runs])
        c0s = np.array([[r["c1"], r["c1"]] for r in runs])
        tcs1, _ = F.extend_tc_profile_below(tcs0, c0s, at_below, min(floor, tcs0[0]), dof1,
                                            step=math.log(2.0) / GM_GRID_PER_OCTAVE)
        runs = [below[tc] for tc in tcs1[:tcs1.size - tcs0.size]] + runs
    grid = np.array([r["tc"] for r in runs])
    c1s = np.array([r["c1"] for r in runs])
    tc_ci, tc_open, inside, _ = F.tc_profile_interval(grid, c1s, c1s, dof1)
    top = null(runs[int(np.argmin(c1s))])
    # sigma_GM: the GLS sd of its coefficient at each Tc of that set; the interval the union
    pos = top["q1"] > 0
    cis = []
    for k in inside:
        r = runs[k]
        pk = r["q1"] > 0
        if not pk[-1]:
            continue
        cov = F._param_cov(r["aw"][:, pk]) * over
        sd = math.sqrt(max(cov[-1, -1], 0.0))
        cis.append(_interval(float(r["q1"][-1]), sd, 0.95))
    cov_top = F._param_cov(top["aw"][:, pos]) * over if np.any(pos) else None
    sd_top = math.sqrt(max(cov_top[-1, -1], 0.0)) if (cov_top is not None and pos[-1]) else math.nan

    def ratios(a: np.ndarray, q: np.ndarray) -> list[float]:
        tot = a @ q
        w = inf[sel] & (tot > 0)
        r = np.sqrt(y[w] / tot[w])
        return [float(r.min()), float(r.max())] if r.size else [math.nan, math.nan]

    def n_out(a: np.ndarray, q: np.ndarray) -> int:  # informative taus outside their 95 % band
        tot = a @ q
        w = inf[sel]
        return int(np.count_nonzero(w & ((tot < lo[sel]) | (tot > hi[sel]))))

    dof0 = max(1, t.size - int(np.count_nonzero(top["q0"])))
    dof_a = max(1, t.size - int(np.count_nonzero(top["q1"])))
    out.update({
        "tested": True, "screen": screen,
        "detected": bool(p < GM_TEST_ALPHA and interior and tested["q1"][-1] > 0),
        "p_value": p, "statistic": stat, "n_looks": n_looks, "best_at_grid_end": not interior,
        "tc_s": float(top["tc"]),
        "tc_ci95_s": list(tc_ci), "tc_ci95_open": tc_open,
        # the Tc range the test searched (the lattice points inside it are the ones
        # evaluated), and the range profiled for the interval (continued below it)
        "tc_grid_s": [float(tc_lo), float(tc_hi)],
        "tc_profile_s": [float(grid[0]), float(grid[-1])],
        "sigma_gm_si": math.sqrt(max(float(top["q1"][-1]), 0.0)),
        "sigma_gm_sd_var_si": sd_top,
        "sigma_gm_ci95_si": ([min(c[0] for c in cis), max(c[1] for c in cis)] if cis
                             else [0.0, math.inf]),
        "chi2_before": float(top["c0"]), "dof_before": dof0,
        "chi2_after": float(top["c1"]), "dof_after": dof_a,
        "ratio_before": ratios(a0, top["q0"]), "ratio_after": ratios(top["a"], top["q1"]),
        "n_informative": int(np.count_nonzero(inf[sel])),
        "n_outside95_before": n_out(a0, top["q0"]), "n_outside95_after": n_out(top["a"], top["q1"]),
        "ieee_after_si2": {k: float(v) for k, v in zip(("Q2_signed", "N2", "B2", "K2", "R2"),
                                                      top["q1"][:5])},
        "tau_range_s": [float(t[0]), float(t[-1])], "model_error_rel": eps,
        "overdispersion": over})
    return out
