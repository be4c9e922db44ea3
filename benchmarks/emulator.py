"""Benchmark of the IMU emulator's noise generation and full error model.

Prints: 12 h at 100 Hz of 6-axis noise with every IEEE 952 term on (Q, N, B as flicker, K, R),
generated in chunks, with one thread and with two threads (gyro and accelerometer triads in
parallel: numpy's generators and scipy's sosfilt release the GIL); and the full error model
(consumer_mems profile, every effect on, 1 kHz internal rate, 100 Hz output).

The gnss-ins-sim figure (about 54 us per 6-axis sample, about 18,500 samples/s) is the
PUBLISHED figure quoted in issue 3, not measured in this run.
Last line: one JSON object of headline figures, units in the keys.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import json  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ThreadPoolExecutor  # noqa: E402

import numpy as np  # noqa: E402

from rigctl.sim.error_model import ImuErrorModel  # noqa: E402
from rigctl.sim.noise import NoiseGenerator  # noqa: E402
from rigctl.sim.profiles import get_profile  # noqa: E402

GNSS_INS_SIM_PUBLISHED_SAMPLES_PER_S = 18_500.0  # published figure (54 us/sample), not measured here
RATE_HZ = 100.0
N_12H = int(12 * 3600 * RATE_HZ)
CHUNK = 1 << 17
GYRO = {"Q": 1e-7, "N": 4.36e-5, "B": 2.42e-6, "K": 8.1e-9, "R": 1e-11, "flicker_tau_min_s": 1.0, "flicker_tau_max_s": 1e4}
ACCEL = {"Q": 1e-6, "N": 1e-3, "B": 4.9e-4, "K": 1e-6, "R": 1e-10, "flicker_tau_min_s": 1.0, "flicker_tau_max_s": 1e4}


def triad(params: dict, seed: int, n: int, chunk: int = CHUNK) -> float:
    """Generate n samples of one 3-axis triad in chunks; returns a checksum (keeps work honest)."""
    gen = NoiseGenerator(params, RATE_HZ, seed)
    acc = 0.0
    for a in range(0, n, chunk):
        y = gen.next(min(chunk, n - a))
        acc += float(y[-1].sum())
    return acc


def best_of(fn, repeats: int = 3) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    one = best_of(lambda: (triad(GYRO, 1, N_12H), triad(ACCEL, 2, N_12H)))
    with ThreadPoolExecutor(2) as pool:
        two = best_of(lambda: [f.result() for f in (pool.submit(triad, GYRO, 1, N_12H), pool.submit(triad, ACCEL, 2, N_12H))])
    sets_1 = N_12H / one
    sets_2 = N_12H / two
    print(f"12 h at 100 Hz, 6 axes, all noise terms: {one:.2f} s on 1 thread, {two:.2f} s on 2 threads")
    print(f"  6-axis samples/s: {sets_1:,.0f} (1 thread), {sets_2:,.0f} (2 threads); "
          f"axis-samples/s: {6 * sets_2:,.0f}")
    print(f"  speedup vs gnss-ins-sim (published ~18,500 samples/s, not measured here): {sets_2 / GNSS_INS_SIM_PUBLISHED_SAMPLES_PER_S:,.0f}x")

    model = ImuErrorModel.from_profile(get_profile("consumer_mems"), seed=1)
    n_full = 60_000  # 10 min at 100 Hz (1 kHz internal)

    def full() -> None:
        for a in range(0, n_full, 20_000):
            g = model.sample_grid(20_000)
            n = len(g.t_internal)
            w = np.zeros((n, 3))
            w[:, 2] = np.sin(0.3 * g.t_eval)
            model.apply(g.t_internal, np.tile([0.0, 0.0, 9.80665], (n, 1)), w)

    t_full = best_of(full, 2)
    full_rate = n_full / t_full
    print(f"full error model, consumer_mems, every effect, 1 kHz internal: {full_rate:,.0f} output samples/s "
          f"({full_rate / RATE_HZ:,.0f}x real time at 100 Hz)")
    print(json.dumps({
        "noise_6axis_samples_per_s_2_threads": round(sets_2),
        "noise_6axis_samples_per_s_1_thread": round(sets_1),
        "noise_axis_samples_per_s_2_threads": round(6 * sets_2),
        "time_12h_100hz_6axis_s_2_threads": round(two, 3),
        "time_12h_100hz_6axis_s_1_thread": round(one, 3),
        "speedup_vs_gnss_ins_sim_published": round(sets_2 / GNSS_INS_SIM_PUBLISHED_SAMPLES_PER_S, 1),
        "gnss_ins_sim_published_samples_per_s": GNSS_INS_SIM_PUBLISHED_SAMPLES_PER_S,
        "full_model_output_samples_per_s_1khz_internal": round(full_rate),
    }))


if __name__ == "__main__":
    main()
