"""What the covariance across taus of a gapped record costs (rigctl.solvers.allan_cov.
gapped_term_covariances), and the joint fit on the real Astro Pi record that needs it.

Cases (best of --repeat, CPU seconds of the calling thread, cache cleared each time):

* astropi: the Astro Pi Sense HAT's x-up section (tests/data/astropi-sensehat-static; 237
  gap-free stretches, 124 distinct lengths, the longest 446 samples), imported with
  `rigctl import` as a user would; the 40 taus the fit uses of `--taus all`. Also the whole
  `rigctl.analysis.allan.compute` of the six axes with `--taus all` and `octave` (CPU of the
  process, both worker threads; wall), and the fit of ax alone with the covariance computed and
  cached.
* dropouts_1pct / dropouts_0.1pct: 12 h at 100 Hz with 1 % / 0.1 % of the samples dropped at
  random (42539 / 4454 stretches), 40 log-spaced factors up to half the longest stretch.
* few_long: five stretches of a 12 h 100 Hz record, against the one-record covariance of the
  same number of samples.

The last line is one JSON object (keys with units: _s CPU seconds, _mb megabytes).
"""
from __future__ import annotations

import argparse
import csv
import datetime as dt
import gzip
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from rigctl import cli  # noqa: E402
from rigctl.analysis import allan as AA  # noqa: E402
from rigctl.solvers import allan_cov as C  # noqa: E402
from rigctl.solvers import allan_fit as F  # noqa: E402

ASTRO = ROOT / "tests" / "data" / "astropi-sensehat-static" / "astro_pi_data_20150824_085954.csv.gz"


def astro_recording(d: Path) -> Path:
    with gzip.open(ASTRO, "rt", newline="") as fh:
        rows = list(csv.DictReader(fh))[3902:]  # the x-up section (its README)
    t0 = dt.datetime.fromisoformat(rows[0]["time_stamp"]).timestamp()
    src = d / "xup.csv"
    with src.open("w") as fh:
        fh.write("t,accel_x,accel_y,accel_z,gyro_x,gyro_y,gyro_z\n")
        for r in rows:
            t = dt.datetime.fromisoformat(r["time_stamp"]).timestamp() - t0
            fh.write(f"{t:.0f},{r['accel_x']},{r['accel_y']},{r['accel_z']},"
                     f"{r['gyro_x']},{r['gyro_y']},{r['gyro_z']}\n")
    seg = d / "sections.json"
    seg.write_text(json.dumps({"x up": {"start": 0, "end": len(rows)}}))
    rec = d / "xup.h5"
    assert cli.main(["import", str(src), "-o", str(rec), "--columns",
                     "time=t,acc_x=accel_x,acc_y=accel_y,acc_z=accel_z,"
                     "gyr_x=gyro_x,gyr_y=gyro_y,gyr_z=gyro_z",
                     "--units", "acc=g,gyr=rad/s,time=s", "--segments", str(seg)]) == 0
    return rec


def cov_cpu(tau0: float, ms: np.ndarray, st: np.ndarray, repeat: int) -> float:
    best = np.inf
    for _ in range(repeat):
        C._gapped_cached.cache_clear()
        C._cached.cache_clear()
        t = time.thread_time()
        C.gapped_term_covariances(tau0, ms, st)
        best = min(best, time.thread_time() - t)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    out: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        rec = astro_recording(Path(tmp))
        calls = []
        orig = F.fit_terms

        def spy(*a, **k):
            calls.append((a, k))
            return orig(*a, **k)

        for taus in ("all", "octave"):
            best_cpu, best_wall = np.inf, np.inf
            for _ in range(args.repeat):
                C._gapped_cached.cache_clear()
                c, w = time.process_time(), time.perf_counter()
                F.fit_terms = spy
                try:
                    AA.compute(str(rec), ["ax", "ay", "az", "gx", "gy", "gz"], taus)
                finally:
                    F.fit_terms = orig
                best_cpu = min(best_cpu, time.process_time() - c)
                best_wall = min(best_wall, time.perf_counter() - w)
            out[f"astropi_compute_6axes_{taus}_cpu_s"] = round(best_cpu, 3)
            out[f"astropi_compute_6axes_{taus}_wall_s"] = round(best_wall, 3)
            print(f"astropi compute, 6 axes, --taus {taus}: {best_cpu:.2f} s CPU, {best_wall:.2f} s wall")
        a, k = next((a, k) for a, k in calls if len(a[0]) > 30)  # an all-tau call
        st = np.asarray(k["stretch_samples"])
        keep = F._thin(len(a[0]), 40)
        ms = np.maximum(1, np.round(np.asarray(a[0])[keep] / k["tau0"])).astype(np.int64)
        out["astropi_stretches"] = int(st.size)
        out["astropi_distinct_lengths"] = int(np.unique(st).size)
        out["astropi_cov_40taus_s"] = round(cov_cpu(k["tau0"], ms, st, args.repeat), 3)
        C._gapped_cached.cache_clear()
        t = time.thread_time()
        orig(*a, **k)
        out["astropi_fit_ax_all_with_cov_s"] = round(time.thread_time() - t, 3)
        t = time.thread_time()
        orig(*a, **k)
        out["astropi_fit_ax_all_cov_cached_s"] = round(time.thread_time() - t, 3)
        print(f"astropi: {st.size} stretches, {np.unique(st).size} lengths; covariance "
              f"{out['astropi_cov_40taus_s']} s, ax fit {out['astropi_fit_ax_all_with_cov_s']} s "
              f"({out['astropi_fit_ax_all_cov_cached_s']} s cached)")
    rng = np.random.default_rng(0)
    n = 4_320_000
    for name, p in (("dropouts_1pct", 0.01), ("dropouts_0.1pct", 0.001)):
        gap = np.flatnonzero(rng.random(n) < p)
        st = np.diff(np.concatenate([[-1], gap, [n]])) - 1
        st = st[st > 0]
        ms = np.unique(np.round(np.logspace(0, np.log10(st.max() / 2 - 1), 40))).astype(np.int64)
        out[f"{name}_stretches"] = int(st.size)
        out[f"{name}_distinct_lengths"] = int(np.unique(st).size)
        out[f"{name}_cov_s"] = round(cov_cpu(0.01, ms, st, args.repeat), 3)
        print(f"{name}: {st.size} stretches, {np.unique(st).size} lengths, {ms.size} taus: "
              f"{out[f'{name}_cov_s']} s")
    st = np.array([1_000_000, 2_000_000, 700_000, 400_000, 220_000])
    ms = np.unique(np.round(np.logspace(0, np.log10(200_000), 40))).astype(np.int64)
    out["few_long_cov_s"] = round(cov_cpu(0.01, ms, st, args.repeat), 3)
    best = np.inf
    for _ in range(args.repeat):
        C._cached.cache_clear()
        t = time.thread_time()
        C.term_covariances(0.01, ms, int(st.sum()) + 1)
        best = min(best, time.thread_time() - t)
    out["few_long_one_record_cov_s"] = round(best, 3)
    print(f"five long stretches: {out['few_long_cov_s']} s (one record: {best:.3f} s)")
    out["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    out["load_1min"] = round(float(Path("/proc/loadavg").read_text().split()[0]), 2)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
