"""The short-record step test's false alarms on REAL static records (rigctl.solvers.allan_step
through rigctl.analysis.allan.compute; docs/allan.md, "Detection limits").

Each set is cut into disjoint windows of ``--minutes`` (5 or 10), a window overlapping a
documented event of the whole record left out (all its axes; the events are listed in
``EVENTS`` with where they are documented), and each window analysed as ``rigctl allan``
analyses a recording of that length (the window's axes in one recording, each axis its own
fit and step test; ``quiet_stretch`` off: the step test runs before it). Every step test is
a false alarm here. Printed per set: axes tested, ``beyond`` (max |z| past its threshold:
the test's alarms before the level-hold condition) and ``found`` (beyond and the level holds:
the alarms now), and each window beyond its threshold with its z and z_hold.

Sets (tests/data): the Galaxy S5 phone gyro (gx, gy, gz, 10 Hz), the ADIS16405 (3 gyros + 3
accelerometers, 100 Hz), the MTi-G gyro x (100 Hz; three windows per recording, as gx, gy,
gz), the MPU-6050 (7.5 min static, 6 axes; one window of 5 minutes). The last line is one
JSON object.
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

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "tests" / "data"
sys.path.insert(0, str(ROOT / "tests"))

from recording_helpers import write_recording  # noqa: E402

from rigctl.analysis import allan as AA  # noqa: E402

G0 = 9.80665
DEG = math.pi / 180.0
#: documented events of the whole records (s), windows overlapping them left out
EVENTS = {
    # docs/allan.md, "Short excursions before the fit": all three gyros dip at 4060-4100 s
    # and at 9040-9137 s
    "galaxy": [(4060.0, 4100.0), (9040.0, 9137.0)],
    # the same section: ay 2150-2478 and 5781-6034 s, 6763-6800 s, 7024-7053 s (ax, az);
    # ax a step at 4673 s; gz a start transient 0-360 s
    "adis": [(0.0, 360.0), (2150.0, 2478.0), (4673.0, 4673.0), (5781.0, 6034.0),
             (6763.0, 6800.0), (7024.0, 7053.0)],
    "mtig": [],
    "mpu": [],
}


def load(name: str) -> tuple[float, dict[str, np.ndarray], str]:
    """(rate in Hz, {axis: samples in SI}, how the windows are put in recordings)."""
    if name == "galaxy":
        g = np.loadtxt(DATA / "galaxy-s5-static" / "gyro_measured_rad_s.csv.gz", delimiter=",",
                       skiprows=1)
        return 10.0, {"gx": g[:, 0], "gy": g[:, 1], "gz": g[:, 2]}, "axes"
    if name == "adis":
        d = DATA / "adis16405-static"
        g = np.loadtxt(d / "gyro_counts.txt.gz") * (0.05 * DEG)
        a = np.loadtxt(d / "accel_counts.txt.gz") * (0.00333 * G0)
        return 100.0, {"ax": a[:, 0], "ay": a[:, 1], "az": a[:, 2],
                       "gx": g[:, 0], "gy": g[:, 1], "gz": g[:, 2]}, "axes"
    if name == "mtig":
        return 100.0, {"gx": np.loadtxt(DATA / "mtig-static-contaminated"
                                        / "gyro_x_rad_s.txt.gz")}, "windows"
    if name == "mpu":  # +-2 g and +-250 deg/s: 16384 and 131 counts per unit
        m = np.loadtxt(DATA / "mpu6050-multipos" / "calibration_data_example_data_tinit_calc.csv",
                       delimiter=",", skiprows=5)
        return 100.0, {"ax": m[:, 0] * G0 / 16384, "ay": m[:, 1] * G0 / 16384,
                       "az": m[:, 2] * G0 / 16384, "gx": m[:, 3] * DEG / 131,
                       "gy": m[:, 4] * DEG / 131, "gz": m[:, 5] * DEG / 131}, "axes"
    raise ValueError(name)


def windows(fs: float, n: int, win: int, events: list[tuple[float, float]]) -> list[int]:
    """First rows of the disjoint windows of ``win`` rows not overlapping an event."""
    out = []
    for j in range(n // win):
        a, b = j * win / fs, (j + 1) * win / fs
        if not any(s < b and e >= a for s, e in events):
            out.append(j * win)
    return out


def run(name: str, minutes: float, tmp: Path) -> dict:
    fs, cols, how = load(name)
    win = int(round(minutes * 60.0 * fs))
    n = min(v.size for v in cols.values())
    starts = windows(fs, n, win, EVENTS[name])
    jobs: list[tuple[str, dict[str, np.ndarray]]] = []
    if how == "axes":
        for r in starts:
            jobs.append((f"{r / fs:.0f} s", {a: v[r:r + win] for a, v in cols.items()}))
    else:  # one axis: three windows per recording
        (v,) = cols.values()
        for i in range(0, len(starts), 3):
            jobs.append((",".join(f"{r / fs:.0f}" for r in starts[i:i + 3]) + " s",
                         {a: v[r:r + win] for a, r in zip(("gx", "gy", "gz"), starts[i:i + 3])}))
    tested = beyond = found = 0
    hits = []
    for label, ax in jobs:
        g = [ax.get(a, np.zeros(win)) for a in ("gx", "gy", "gz")]
        kw = {"angular_rate": np.column_stack(g)}
        if "ax" in ax:
            kw["specific_force"] = np.column_stack([ax[a] for a in ("ax", "ay", "az")])
        path = write_recording(tmp / "w.h5", fs, **kw)
        res = AA.compute(str(path), list(ax), gaps="skip", quiet_stretch=False)["axes"]
        path.unlink()
        for a in ax:
            st = res[a]["excursions"].get("step_test") or {}
            if not st.get("tested"):
                continue
            tested += 1
            beyond += st["beyond"]
            found += st["found"]
            if st["beyond"]:
                hits.append({"window": label, "axis": a, "z": round(st["z"], 2),
                             "threshold_z": round(st["threshold_z"], 2),
                             "t_s": st["t_s"], "z_hold": round(st["hold"]["z"], 2),
                             "found": st["found"]})
    return {"tested": tested, "beyond": beyond, "found": found, "windows": len(jobs),
            "hits": hits}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default="galaxy,adis,mtig,mpu")
    ap.add_argument("--minutes", default="5,10")
    a = ap.parse_args()
    out: dict = {}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        for name in a.sets.split(","):
            for m in (float(v) for v in a.minutes.split(",")):
                if name == "mpu" and m > 7.0:
                    continue
                r = run(name, m, Path(d))
                out[f"{name} {m:g} min"] = r
                print(f"{name} {m:g} min: {r['tested']} axes tested, beyond the threshold "
                      f"{r['beyond']}, found (the level holds) {r['found']}", flush=True)
                for h in r["hits"]:
                    print("    ", h, flush=True)
    print(f"{time.perf_counter() - t0:.0f} s")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
