"""Allan analysis benchmark (issue 4). Last line: one JSON object of headline figures.

Parts (select with --parts, default all):
  axis   one 12 h x 2 kHz axis (8.64e7 samples, ~95 log-spaced taus): fast mode, exact mode,
         allantools.oadev (full length, or --allantools-slice N samples and scaled linearly,
         which the output then says), exact vs allantools max relative difference.
  h5     a 6-axis 12 h x 2 kHz HDF5 recording (written with h5py to a temp dir) analysed and
         fitted by `rigctl allan` in a subprocess: wall time and peak RSS (ru_maxrss).
  fit    joint fit vs piecewise read-offs on synthetic captures with known N, B, K
         (white + octave Gauss-Markov flicker bank + random walk), --seeds per profile:
         errors, and 95 % interval coverage of the joint fit.
"""
from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from scipy.signal import lfilter  # noqa: E402

from rigctl.solvers import allan as A  # noqa: E402
from rigctl.solvers import allan_edf as E  # noqa: E402
from rigctl.solvers import allan_fit as F  # noqa: E402

D2R = math.pi / 180.0
FS = 2000.0
N12H = int(12 * 3600 * FS)
PROFILES = {  # gyro truths: N deg/sqrt(h), B deg/h, K deg/h/sqrt(h)
    "mems_grade": (0.2, 5.0, 10.0),
    "tactical": (0.05, 1.0, 2.0),
}


def synth_rate(n: int, fs: float, n_arw: float, b: float, k: float, seed: int) -> np.ndarray:
    """White + flicker (octave Gauss-Markov bank, PSD B^2/(2 pi f)) + random walk (SI)."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / fs
    y = rng.standard_normal(n) * (n_arw / math.sqrt(dt))
    if b > 0:
        q = b * b * math.log(2.0) / math.pi
        tc = 0.5
        while tc <= 4 * n * dt:
            rep = max(1, int(round(tc / 16.0 / dt)))
            phi = math.exp(-rep * dt / tc)
            w = rng.standard_normal(-(-n // rep)) * math.sqrt(q * (1 - phi * phi))
            g = lfilter([1.0], [1.0, -phi], w, zi=[rng.standard_normal() * math.sqrt(q) * phi])[0]
            y += np.repeat(g, rep)[:n]
            tc *= 2.0
    if k > 0:
        y += np.cumsum(rng.standard_normal(n)) * (k * math.sqrt(dt))
    return y


def part_axis(slice_n: int | None) -> dict:
    y = synth_rate(N12H, FS, 0.2 * D2R / 60, 0.0, 10 * D2R / 3600 / 60, seed=1)
    t = time.perf_counter()
    fast = A.oadev(y, 1 / FS, 95, data_type="rate", mode="fast")
    t_fast = time.perf_counter() - t
    t = time.perf_counter()
    exact = A.oadev(y, 1 / FS, 95, data_type="rate", mode="exact")
    t_exact = time.perf_counter() - t
    print(f"fast mode: {fast.m.size} taus in {t_fast:.2f} s; exact mode: {exact.m.size} taus "
          f"in {t_exact:.2f} s")
    import allantools

    yy = y if slice_n is None else y[:slice_n]
    taus = exact.tau_s[exact.m <= A.max_factor(yy.size + 1, "oadev")]
    t = time.perf_counter()
    _, devs, _, _ = allantools.oadev(yy, rate=FS, data_type="freq", taus=taus)
    t_at = time.perf_counter() - t
    scale = 1.0 if slice_n is None else N12H / yy.size
    note = ("allantools run on the full 8.64e7 samples" if slice_n is None else
            f"allantools run on {yy.size} samples, time scaled x{scale:.1f} (linear)")
    t_at_full = t_at * scale
    mine = exact.dev[: devs.size] if slice_n is None else A.oadev(
        yy, 1 / FS, exact.m[exact.m <= A.max_factor(yy.size + 1, "oadev")], "rate",
        mode="exact").dev
    rel = float(np.max(np.abs(mine / devs - 1)))
    print(f"allantools.oadev: {t_at:.2f} s ({note}); exact vs allantools max rel diff {rel:.1e}")
    return {"fast_s": t_fast, "exact_s": t_exact, "allantools_s": t_at_full,
            "speedup_fast_vs_allantools": t_at_full / t_fast,
            "speedup_exact_vs_allantools": t_at_full / t_exact, "exact_vs_allantools_rel": rel,
            "n_taus": int(fast.m.size), "allantools_note": note}


def write_h5(path: str, n: int) -> None:
    import h5py

    chunk = 1 << 20
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "rigctl-recording"
        f.attrs["schema_version"] = 1
        imu = f.create_group("imu")
        imu.attrs["sample_rate_hz"] = FS
        g = imu.create_dataset("angular_rate", (n, 3), "f8", chunks=(65536, 3))
        a = imu.create_dataset("specific_force", (n, 3), "f8", chunks=(65536, 3))
        g.attrs["units"], a.attrs["units"] = "rad/s", "m/s^2"
        rng = np.random.default_rng(5)
        rw = np.zeros(6)
        for s in range(0, n, chunk):
            m = min(chunk, n - s)
            w = rng.standard_normal((m, 6))
            steps = np.cumsum(rng.standard_normal((m, 6)), axis=0) * 1e-7 + rw
            rw = steps[-1]
            g[s: s + m] = w[:, :3] * 2e-3 + steps[:, :3]
            a[s: s + m] = w[:, 3:] * 1e-3 + steps[:, 3:] + [0.0, 0.0, 9.80665]


def part_h5() -> dict:
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "rec12h.h5")
        t = time.perf_counter()
        write_h5(path, N12H)
        print(f"wrote 6-axis 12 h recording ({os.path.getsize(path) / 1e9:.2f} GB) in "
              f"{time.perf_counter() - t:.1f} s")
        code = ("import resource,sys,time,argparse\n"
                "from rigctl import allan_cmd\n"
                "p=argparse.ArgumentParser();s=p.add_subparsers();allan_cmd.register(s)\n"
                f"a=p.parse_args(['allan',{path!r}])\n"
                "import io,contextlib\nbuf=io.StringIO()\n"
                "t=time.perf_counter()\n"
                "with contextlib.redirect_stdout(buf): rc=a.func(a)\n"
                "dt=time.perf_counter()-t\n"
                "print(rc,dt,resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)\n")
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             env=os.environ.copy(), check=True).stdout.split()
    rc, dt, rss_kb = int(out[0]), float(out[1]), float(out[2])
    print(f"rigctl allan on 6 x 8.64e7 samples: exit {rc}, {dt:.1f} s, peak RSS "
          f"{rss_kb / 1024:.0f} MB")
    return {"h5_6axis_s": dt, "h5_peak_rss_MB": rss_kb / 1024.0, "h5_exit": rc}


def part_fit(seeds: int, fs: float) -> dict:
    n = int(12 * 3600 * fs)
    errs: dict[str, dict[str, list[float]]] = {}
    cover: list[bool] = []
    print(f"joint fit vs piecewise, {seeds} seeds per profile, 12 h at {fs:g} Hz "
          "(synthetic emulator-like data with known truth)")
    print(f"{'profile':>11} {'term':>4} {'truth':>8} {'joint_err_%':>12} {'piecewise_err_%':>16}")
    for prof, (nt, bt, kt) in PROFILES.items():
        truth = {"N": nt * D2R / 60, "B": bt * D2R / 3600, "K": kt * D2R / 3600 / 60}
        rows = {t: ([], []) for t in truth}
        for seed in range(seeds):
            y = synth_rate(n, fs, truth["N"], truth["B"], truth["K"], seed=100 + seed)
            r = A.oadev(y, 1 / fs, 95, "rate")
            x = A.phase_from_rate(y, 1 / fs)
            c = E.confidence("oadev", x, r.m, r.dev)
            fit = F.fit_terms(r.tau_s, r.dev, c["edf"], "gyro")
            pw = F.piecewise_readoffs(r.tau_s, r.dev, "gyro")["si"]
            for t, tv in truth.items():
                j = F.term_value_si(fit, t)
                rows[t][0].append(abs(j / tv - 1))
                rows[t][1].append(abs((pw[t] or 0.0) / tv - 1))
                e = fit["terms"][t]
                si = F.SI_UNITS["gyro"][t]
                if e["supported"]:
                    lo, hi = e[f"ci95_{si}"]
                    cover.append(lo <= tv <= hi)
                else:
                    cover.append(tv <= e[f"upper95_{si}"])
        for t in truth:
            je, pe = np.mean(rows[t][0]) * 100, np.mean(rows[t][1]) * 100
            errs.setdefault(prof, {})[t] = [je, pe]
            print(f"{prof:>11} {t:>4} {PROFILES[prof]['NBK'.index(t)]:8.3g} {je:12.2f} {pe:16.2f}")
    cov = float(np.mean(cover))
    print(f"joint-fit 95 % interval coverage of the truth: {cov * 100:.0f} % of {len(cover)}")
    joint_better = all(v[0] < v[1] for p in errs.values() for v in p.values())
    return {"fit_coverage95_pct": cov * 100, "joint_better_than_piecewise": joint_better,
            "fit_errors_pct": errs}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default="axis,h5,fit")
    ap.add_argument("--allantools-slice", type=int, default=None,
                    help="run allantools on this many samples and scale (default: full)")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--fit-rate-hz", type=float, default=100.0)
    a = ap.parse_args()
    parts = a.parts.split(",")
    res: dict = {}
    if "axis" in parts:
        res.update(part_axis(a.allantools_slice))
    if "h5" in parts:
        res.update(part_h5())
    if "fit" in parts:
        res.update(part_fit(a.seeds, a.fit_rate_hz))
    print(json.dumps({k: v for k, v in res.items() if k != "fit_errors_pct"}))


if __name__ == "__main__":
    main()
