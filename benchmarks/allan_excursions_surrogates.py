"""The excursion detector (rigctl.solvers.allan_excursions) on surrogates of real records
with non-Gaussian, quantized or skewed white noise, and its power on emulated events.

    python benchmarks/allan_excursions_surrogates.py [--shuffled 100] [--iaaft 50]
                                                     [--phone 17] [--power 30]

* **Keysight 53230A** (tests/data/stable32-reference, the time-interval counter's noise
  floor: 55,688 phase readings at 1 s, white PM, quantized to ~5 ps, skewed): the phase
  readings shuffled (``--shuffled`` surrogates: their own distribution, white -- exactly the
  null of white PM) and IAAFT surrogates of the phase (``--iaaft``: the same spectrum and the
  same distribution of values). The detector runs on the frequency y = diff(x) / tau0, as
  rigctl's pipeline for an --integrated record. Also Gaussian white phase of the readings'
  sd, raw and quantized to the readings' 5 ps (as many as --shuffled): the control.
* **Galaxy S5** (tests/data/galaxy-s5-static, the phone's three gyros, 10 Hz, 6 h): IAAFT
  surrogates of each axis' rate (``--phone`` per axis): its spectrum and its dwelling,
  quantized output kept.
* **Power** (``--power`` seeds): an emulated tactical accelerometer axis (6 h at 10 Hz,
  rigctl.sim.noise, as tests/test_allan_excursions.py) with a 240 s bump of 6, 7, 8 and 10
  times sigma_A(300 s), and a level shift of 6 sigma_A(300 s) at 3/4 of the record: how often
  an excursion (level shift) is found within 30 s of its time.

IAAFT (Schreiber & Schmitz 1996): start from a random shuffle, then alternately impose the
record's Fourier amplitudes and its values by rank, until the ranks stop changing (at most 100
iterations); the surrogate is the last rank remap (exactly the record's values). Each
surrogate has its own seed (``--first-seed`` + i). A detection: any excursion or level shift.
Counts with Clopper-Pearson 95 % intervals, against the stated family-wise 1 % per axis.

Last line: one JSON object.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
from allan_excursions import block_means, clopper_pearson, detect  # noqa: E402

DATA = ROOT / "tests" / "data"
KEYSIGHT = DATA / "stable32-reference" / "Keysight53230A_ti_noise_floor" / "tic_phase.txt"
PHONE = DATA / "galaxy-s5-static" / "gyro_measured_rad_s.csv.gz"


def iaaft(x: np.ndarray, rng: np.random.Generator, max_iter: int = 100) -> np.ndarray:
    """An IAAFT surrogate of x: its Fourier amplitudes and (exactly) its values."""
    amp = np.abs(np.fft.rfft(x))
    values = np.sort(x)
    s = rng.permutation(x)
    ranks = None
    for _ in range(max_iter):
        f = np.fft.rfft(s)
        s = np.fft.irfft(amp * np.exp(1j * np.angle(f)), n=x.size)
        r = np.argsort(np.argsort(s))
        s = values[r]
        if ranks is not None and np.array_equal(r, ranks):
            break
        ranks = r
    return s


def count(trials, label: str) -> dict:
    k = n = 0
    found = []
    for name, y, tau0 in trials:
        r = detect(y, tau0)
        n += 1
        if r.get("excursions"):
            k += 1
            found.append(name + ": " + "; ".join(
                f"{e['kind']} {e['start_s']:.0f}-{e['end_s']:.0f} s z {e['z_start']:.2f}/{e['z_end']:.2f}"
                for e in r["excursions"]))
    lo, hi = clopper_pearson(k, n)
    print(f"{label}: {k} of {n} with a detection (Clopper-Pearson 95 % [{100 * lo:.1f}, "
          f"{100 * hi:.1f}] %)", flush=True)
    for f in found:
        print("   ", f, flush=True)
    return {"detections": k, "trials": n, "cp95_pct": [100 * lo, 100 * hi]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shuffled", type=int, default=100)
    ap.add_argument("--iaaft", type=int, default=50)
    ap.add_argument("--phone", type=int, default=17, help="IAAFT surrogates per phone axis")
    ap.add_argument("--power", type=int, default=30)
    ap.add_argument("--first-seed", type=int, default=1)
    args = ap.parse_args()
    t0 = time.perf_counter()
    out: dict = {}
    s0 = args.first_seed
    if KEYSIGHT.is_file():
        x = np.loadtxt(KEYSIGHT, comments=["#", "%"])
        r = detect(np.diff(x), 1.0)
        print("Keysight record:", [f"{e['kind']} {e['start_s']:.0f} s" for e in r["excursions"]])
        out["keysight_record_detections"] = len(r["excursions"])
        sd, q = float(np.std(x)), float(np.median(np.diff(np.unique(x))))  # the readings' step
        out["keysight_shuffled"] = count(
            ((f"seed {s}", np.diff(np.random.default_rng(s).permutation(x)), 1.0)
             for s in range(s0, s0 + args.shuffled)), "Keysight phase shuffled")
        out["keysight_iaaft"] = count(
            ((f"seed {s}", np.diff(iaaft(x, np.random.default_rng(s))), 1.0)
             for s in range(s0, s0 + args.iaaft)), "Keysight phase IAAFT")
        out["gaussian_white_pm"] = count(
            ((f"seed {s}", np.diff(np.random.default_rng(s).normal(0, sd, x.size)), 1.0)
             for s in range(s0, s0 + args.shuffled)), "Gaussian white PM, the readings' sd")
        out["gaussian_white_pm_quantized"] = count(
            ((f"seed {s}", np.diff(np.round(np.random.default_rng(s).normal(0, sd, x.size) / q) * q), 1.0)
             for s in range(s0, s0 + args.shuffled)), f"the same quantized to {q * 1e12:.1f} ps")
    if PHONE.is_file() and args.phone:
        y = np.loadtxt(PHONE, delimiter=",", skiprows=1)
        out["phone_iaaft"] = count(
            ((f"g{'xyz'[i]} seed {s}", iaaft(y[:, i], np.random.default_rng([s, i])), 0.1)
             for i in range(3) for s in range(s0, s0 + args.phone)), "Galaxy S5 gyros IAAFT")
    if args.power:
        sys.path.insert(0, str(ROOT / "tests"))
        from test_allan_excursions import _emulated

        rate = 10.0
        found: dict[str, int] = {}
        for s in range(s0, s0 + args.power):
            y0, sig = _emulated(seed=1000 + s)
            n = y0.size
            cases = {f"bump {k:g} sd": (k, 9000.0, 9240.0) for k in (6.0, 7.0, 8.0, 10.0)}
            cases["level shift 6 sd"] = (6.0, 0.75 * n / rate, n / rate)
            for name, (k, a, b) in cases.items():
                y = y0.copy()
                y[int(a * rate):int(b * rate)] += k * sig
                ex = detect(y, 1.0 / rate).get("excursions", [])
                found[name] = found.get(name, 0) + any(abs(e["start_s"] - a) <= 30.0 for e in ex)
        for name, k in found.items():
            print(f"power, {name}: found at its time in {k} of {args.power}", flush=True)
        out["power_found_of"] = {k: [v, args.power] for k, v in found.items()}
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    out["load_1min"] = os.getloadavg()[0]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
