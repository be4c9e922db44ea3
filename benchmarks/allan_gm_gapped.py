"""What the Gauss-Markov check of one axis costs where the record has gaps (its own, or windows
left out by --excursions exclude): rigctl.solvers.allan_gm.gm_candidate on the pooled
estimator's covariance (allan_cov.gapped_term_covariances with the GM kernel, one per Tc of
its grid, ~75-115 Tc), with the compiled pair loop (allan_cov_kernels) and with the numpy
loop it replaced (kept as the fallback without numba: allan_cov_kernels.HAVE_NUMBA False,
with the contiguous kernel for long stretches), in the same run.

    python benchmarks/allan_gm_gapped.py [--hours 4] [--rec-file PATH] [--skip-long]
                                         [--cases two_piece,long_gapped] [--compiled-only]

``--compiled-only`` times the compiled loop alone (the numpy loop takes ~60-75 s a case);
``--cases`` picks the cases (--skip-long: two_piece alone). Comparing two versions of the
code on a shared machine: run each with NUMBA_NUM_THREADS=1, interleaved, several times, and
compare the CPU seconds (wall time follows the load; the thread CPU here does not).

Cases (thread CPU seconds of gm_candidate, every covariance cache cleared before each run):

* two_piece: 30,000 samples at 100 Hz (white FM 1e-3, a random walk, a Gauss-Markov bump of
  Tc 2 s) with rows 13000-14000 left out (`drop`, as --excursions exclude does): stretches of
  13000 and 16000 samples, both below allan_cov.GM_LONG_MIN, so every pair goes through the
  pair loop.
* long_gapped: one axis (gx) of a --hours x 2 kHz file written by rigctl's Recorder
  (benchmarks/allan.py write_recorder_h5, 3 gaps per hour of 1-2000 samples: 13 stretches at
  4 h, as the 12 gaps of the 12 h `rec` part), read by rigctl.analysis.allan; compiled,
  every stretch goes through the pair loop (6.9 s thread CPU for 76 Tc at load 3-4; 16.2 s
  while the 4 longest went through the contiguous kernel); without numba the 4 longest go
  through the contiguous kernel (GM_LONG_LENGTHS), the rest through the numpy loop.
  The file is written to a temporary directory (2 GB at 4 h; ~110 s) unless --rec-file names
  one (kept; written there if missing).

The curve, EDFs and stretches each case's gm_candidate gets are those rigctl.analysis.allan
hands it (captured from its call of allan_drift.gauss_markov, which runs the candidate only
where the self-check saw a stationary bump; here it is timed whatever the check saw).
Last line: one JSON object (keys with units: _s thread CPU seconds).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.signal import lfilter

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))
from rigctl.analysis import allan as AA  # noqa: E402
from rigctl.analysis import allan_drift as AD  # noqa: E402
from rigctl.solvers import allan_cov as C  # noqa: E402
from rigctl.solvers import allan_cov_kernels as KC  # noqa: E402
from rigctl.solvers import allan_gm as GM  # noqa: E402

CACHES = ("_cached", "_gapped_cached", "_gm_cached", "_gm_gapped_cached", "_gm_nodes",
          "_gm_gapped_pairs")


def candidate_inputs(path: str, axis: str, drop: list | None = None) -> dict:
    """What rigctl.analysis.allan hands the Gauss-Markov check of ``axis``."""
    got: dict = {}
    orig = AD.gauss_markov

    def capture(fit, tau, dev, edf, tau0, n_phase, sensor, stretch_samples=None):
        got.update(tau=tau, dev=dev, edf=edf, tau0=tau0, n_phase=n_phase,
                   stretch_samples=stretch_samples)
        return orig(fit, tau, dev, edf, tau0, n_phase, sensor, stretch_samples)

    AD.gauss_markov = capture
    try:
        AA.compute_once(path, [axis], 95, False, drop=drop)
    finally:
        AD.gauss_markov = orig
    if got.get("stretch_samples") is None:
        raise SystemExit(f"{path}: no gaps reached the Gauss-Markov check")
    return got


def timed_check(inp: dict, compiled: bool) -> tuple[float, int, dict]:
    """Thread CPU s of gm_candidate, the number of Tc it tried, and its result."""
    for name in CACHES:
        getattr(C, name).cache_clear()
    calls = []
    orig = C._gm_gapped

    def count(*a):
        calls.append(a[-1])
        return orig(*a)

    prev = KC.HAVE_NUMBA
    KC.HAVE_NUMBA = prev and compiled
    C._gm_gapped = count
    try:
        t = time.thread_time()
        res = GM.gm_candidate(inp["tau"], inp["dev"], inp["edf"], inp["tau0"], inp["n_phase"],
                              stretch_samples=inp["stretch_samples"])
        return time.thread_time() - t, len(calls), res
    finally:
        KC.HAVE_NUMBA = prev
        C._gm_gapped = orig


def two_piece(d: str) -> dict:
    from recording_helpers import write_recording

    n, fs = 30_000, 100.0
    rng = np.random.default_rng(5)
    y = rng.standard_normal(n) * 1e-3 + np.cumsum(rng.standard_normal(n)) * 2e-6 + 0.01
    a = math.exp(-1.0 / (fs * 2.0))
    y += lfilter([1.0], [1.0, -a], rng.standard_normal(n)) * 3e-4
    p = Path(d) / "two_piece.h5"
    g = np.column_stack([y, np.full(n, 1e-3), np.full(n, -1e-3)])
    write_recording(p, fs, counter=np.arange(n, dtype=np.uint64), angular_rate=g)
    return candidate_inputs(str(p), "gx", drop=[(13_000, 14_000)])


def long_gapped(d: str, hours: float, rec_file: str | None) -> dict:
    import allan as B

    path = rec_file or os.path.join(d, "gapped.h5")
    if not os.path.exists(path):
        t = time.perf_counter()
        B.write_recorder_h5(path, int(hours * 3600 * B.FS), gaps_per_hour=3.0,
                            rows_per_flush=4000)
        print(f"wrote {path} ({os.path.getsize(path) / 1e9:.2f} GB) in "
              f"{time.perf_counter() - t:.0f} s", flush=True)
    return candidate_inputs(path, "gx")


def measure(name: str, inp: dict, compiled_only: bool = False) -> dict:
    st = np.asarray(inp["stretch_samples"])
    print(f"{name}: {st.size} stretches ({st.min()}..{st.max()} samples), tau0 {inp['tau0']} s, "
          f"{len(inp['tau'])} taus", flush=True)
    new, n_tc, r_new = timed_check(inp, compiled=True)
    if compiled_only:
        print(f"  compiled pair loop: {new:.2f} s ({n_tc} Tc); result "
              f"{ {k: r_new.get(k) for k in ('tested', 'detected', 'tc_s', 'p_value')} }",
              flush=True)
        return {f"{name}_gm_check_s": round(new, 3), f"{name}_tc_count": n_tc,
                f"{name}_stretches": int(st.size)}
    old, n_tc_old, r_old = timed_check(inp, compiled=False)
    print(f"  compiled pair loop: {new:.2f} s ({n_tc} Tc); numpy loop: {old:.2f} s "
          f"({n_tc_old} Tc); {old / new:.1f}x", flush=True)
    same = {k: (r_new.get(k), r_old.get(k)) for k in ("tested", "detected", "tc_s", "p_value")}
    print(f"  results (compiled, numpy): {same}", flush=True)
    return {f"{name}_gm_check_s": round(new, 3), f"{name}_gm_check_before_s": round(old, 3),
            f"{name}_speedup": round(old / new, 2), f"{name}_tc_count": n_tc,
            f"{name}_stretches": int(st.size),
            f"{name}_same_result": bool(r_new.get("tc_s") == r_old.get("tc_s")
                                        and r_new.get("detected") == r_old.get("detected"))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--hours", type=float, default=4.0)
    ap.add_argument("--rec-file", default=None)
    ap.add_argument("--skip-long", action="store_true")
    ap.add_argument("--cases", default="two_piece,long_gapped",
                    help="comma-separated, of two_piece, long_gapped")
    ap.add_argument("--compiled-only", action="store_true",
                    help="time the compiled pair loop only, not the numpy loop")
    args = ap.parse_args()
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    bad = sorted(set(cases) - {"two_piece", "long_gapped"})
    if bad:
        raise SystemExit(f"--cases: unknown case {', '.join(bad)} (two_piece, long_gapped)")
    if args.skip_long and "long_gapped" in cases:
        cases.remove("long_gapped")
    if not KC.HAVE_NUMBA:
        raise SystemExit("numba is not installed (the `fast` extra): nothing to compare")
    C._gm_gapped_loop(0.01, np.array([4.0, 6.0]), np.array([50, 60]), np.array([1, 1]), 0.05)
    out: dict = {"load_avg_before": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory(dir="/tmp") as d:
        if "two_piece" in cases:
            out.update(measure("two_piece", two_piece(d), args.compiled_only))
        if "long_gapped" in cases:
            out["long_gapped_hours"] = args.hours
            out.update(measure("long_gapped", long_gapped(d, args.hours, args.rec_file),
                               args.compiled_only))
    out["load_avg_after"] = os.getloadavg()[0]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
