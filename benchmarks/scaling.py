"""How each cost grows with the work (issue 21 item 4): captures of 1 h, 12 h and 48 h at
100 Hz and 2 kHz.

For every (hours, rate) case, on one synthetic axis (white noise + rate random walk + an
offset) with 95 log-spaced taus:

  exact      rigctl.solvers.allan.oadev(mode="exact"): every term of every tau (compiled
             kernel, allan.THREADS threads)
  strided    oadev(mode="fast"): all terms below m = 16, stride m/16..m/8 above
  phase      the float64 phase alone (one sequential pass)
  noise      the emulator's 6-axis noise (rigctl.sim.noise.NoiseGenerator, two triads, every
             IEEE 952 term) for the same number of samples (skipped above --noise-max samples:
             it is linear and 48 h x 2 kHz would take minutes of a shared machine)

Each cost is printed as wall and CPU seconds (best of --repeats) beside the work it does
(samples; for exact also the number of terms, sum over taus of N - 2m), then fitted as
cost ~ work^p over the cases (least squares in log-log); p = 1 is linear. CPU time is the
figure to read on a loaded machine (the load average is printed). Last line: one JSON object.
"""
from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from rigctl.solvers import allan as A  # noqa: E402

HOURS = (1.0, 12.0, 48.0)
RATES = (100.0, 2000.0)
NOISE = {"N": 1e-3, "B": 2e-5, "K": 1e-6, "R": 0.0, "Q": 0.0, "flicker_tau_min_s": 1.0,
         "flicker_tau_max_s": 1e4}


def _load() -> str:
    return "/".join(f"{v:.2f}" for v in os.getloadavg())


def _best(fn, repeats: int) -> tuple[float, float]:
    """(best wall s, best CPU s of this process incl. threads) over ``repeats`` calls."""
    walls, cpus = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    return min(walls), min(cpus)


def _series(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    y = np.empty(n)
    step = 1 << 22
    level = 0.0
    for a in range(0, n, step):
        m = min(step, n - a)
        rw = np.cumsum(rng.standard_normal(m)) * 1e-7 + level
        level = float(rw[-1])
        y[a: a + m] = rng.standard_normal(m) * 1e-3 + rw
    y += 9.80665
    return y


def _noise(n: int, fs: float) -> None:
    from rigctl.sim.noise import NoiseGenerator
    from rigctl.solvers.noise_coefficients import triad

    for seed in (1, 2):
        gen = NoiseGenerator(triad(**NOISE), fs, seed)
        for a in range(0, n, 1 << 17):
            gen.next(min(1 << 17, n - a))


def _exponent(work: list[float], cost: list[float]) -> float:
    if len(work) < 2:
        return float("nan")
    return float(np.polyfit(np.log(work), np.log(cost), 1)[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--noise-max", type=float, default=1e8,
                    help="largest sample count for the emulator noise (linear; default 1e8)")
    ap.add_argument("--max-samples", type=float, default=4e8,
                    help="skip cases above this many samples (48 h x 2 kHz is 3.5e8: ~6 GB)")
    a = ap.parse_args()
    A.oadev(np.random.default_rng(0).standard_normal(300_000), 0.01, 20, mode="exact")
    A.oadev(np.random.default_rng(0).standard_normal(2_000_000), 0.01, 20, mode="fast")
    rows = []
    print(f"{'hours':>5} {'rate_Hz':>7} {'samples':>11} {'exact_terms':>12} "
          f"{'exact_s':>8} {'exact_cpu_s':>11} {'strided_s':>9} {'strided_cpu_s':>13} "
          f"{'phase_cpu_s':>11} {'noise6_cpu_s':>12}  load")
    for fs in RATES:
        for h in HOURS:
            n = int(h * 3600 * fs)
            if n > a.max_samples:
                print(f"{h:5g} {fs:7g} {n:11d}  skipped (--max-samples {a.max_samples:g})")
                continue
            y = _series(n, 1)
            ms = A.tau_factors(n + 1, 95)
            terms = float(np.sum(n + 1 - 2 * ms))
            load = _load()
            ex = _best(lambda: A.oadev(y, 1 / fs, 95, mode="exact"), a.repeats)
            st = _best(lambda: A.oadev(y, 1 / fs, 95, mode="fast"), a.repeats)
            ph = _best(lambda: A.phase_from_rate(y, 1 / fs), a.repeats)
            nz = _best(lambda: _noise(n, fs), 1) if n <= a.noise_max else (np.nan, np.nan)
            del y
            rows.append({"hours": h, "rate_hz": fs, "samples": n, "exact_terms": terms,
                         "exact_s": ex[0], "exact_cpu_s": ex[1], "strided_s": st[0],
                         "strided_cpu_s": st[1], "phase_cpu_s": ph[1], "noise6_cpu_s": nz[1]})
            print(f"{h:5g} {fs:7g} {n:11d} {terms:12.3e} {ex[0]:8.2f} {ex[1]:11.2f} "
                  f"{st[0]:9.2f} {st[1]:13.2f} {ph[1]:11.3f} {nz[1]:12.2f}  {load}", flush=True)
    out: dict = {"cases": len(rows), "load_avg_end": _load()}
    if rows:
        smp = [r["samples"] for r in rows]
        fits = {
            "exact_cpu_exponent_vs_samples": _exponent(smp, [r["exact_cpu_s"] for r in rows]),
            "exact_cpu_exponent_vs_terms": _exponent([r["exact_terms"] for r in rows],
                                                     [r["exact_cpu_s"] for r in rows]),
            "strided_cpu_exponent_vs_samples": _exponent(smp, [r["strided_cpu_s"] for r in rows]),
            "phase_cpu_exponent_vs_samples": _exponent(smp, [r["phase_cpu_s"] for r in rows]),
        }
        nz = [(r["samples"], r["noise6_cpu_s"]) for r in rows if np.isfinite(r["noise6_cpu_s"])]
        fits["noise6_cpu_exponent_vs_samples"] = _exponent([s for s, _ in nz], [c for _, c in nz])
        print("exponents p of cost ~ work^p (CPU time, log-log least squares): " +
              ", ".join(f"{k.replace('_cpu_exponent', '')} {v:.2f}" for k, v in fits.items()))
        per = {f"exact_cpu_ns_per_term_{r['hours']:g}h_{r['rate_hz']:g}hz":
               1e9 * r["exact_cpu_s"] / r["exact_terms"] for r in rows}
        out.update(fits)
        out.update(per)
        for r in rows:
            tag = f"{r['hours']:g}h_{r['rate_hz']:g}hz"
            out[f"exact_cpu_s_{tag}"] = r["exact_cpu_s"]
            out[f"strided_cpu_s_{tag}"] = r["strided_cpu_s"]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
