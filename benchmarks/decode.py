"""MTData2 decode throughput of the vectorised decoder (rigctl.drivers.xsens_decode).

Frames: PacketCounter, SampleTimeFine, Acceleration, RateOfTurn, Temperature, StatusWord
(float32), 61 bytes each. Measures frames decoded per second (a) from one large buffer,
(b) streaming in 256 KiB feeds, (c) streaming with byte errors at 1e-4. For scale, a 921.6 kbaud
8N1 line carries 921600 / 10 / 61 = 1,511 such frames per second (about 2,300 for a 40-byte frame).
Target: >= 1e6 frames/s. Last line: one JSON object.

Usage: python benchmarks/decode.py [n_frames]
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from rigctl.drivers import xsens as X  # noqa: E402
from rigctl.drivers.xsens_decode import MTData2Stream, decode_buffer  # noqa: E402

XDIS = [X.XDI.PACKET_COUNTER, X.XDI.SAMPLE_TIME_FINE, X.XDI.ACCELERATION, X.XDI.RATE_OF_TURN,
        X.XDI.TEMPERATURE, X.XDI.STATUS_WORD]


def make_stream(n: int, seed: int = 0) -> tuple[bytes, int]:
    rng = np.random.default_rng(seed)
    f = {"packet_counter": np.arange(n), "sample_time_fine": 5 * np.arange(n),
         "acceleration": rng.normal(0, 9.8, (n, 3)), "rate_of_turn": rng.normal(0, 1, (n, 3)),
         "temperature": rng.normal(30, 1, n), "status_word": np.zeros(n, dtype=np.int64)}
    arr = X.encode_mtdata2(XDIS, f)
    return arr.tobytes(), arr.shape[1]


def best_of(fn, repeats: int = 3) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def stream_decode(data: bytes, chunk: int) -> MTData2Stream:
    st = MTData2Stream()
    view = memoryview(data)
    for i in range(0, len(data), chunk):
        st.feed(view[i:i + chunk])
    st.flush()
    return st


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000
    data, frame_len = make_stream(n)
    rng = np.random.default_rng(1)
    noisy = np.frombuffer(data, np.uint8).copy()
    pos = np.flatnonzero(rng.random(noisy.size) < 1e-4)
    noisy[pos] ^= rng.integers(1, 256, pos.size).astype(np.uint8)
    noisy_b = noisy.tobytes()
    chunk = 256 * 1024

    batch, c = decode_buffer(data)
    assert len(batch) == n and c.bad_frames == 0
    st = stream_decode(noisy_b, chunk)
    hit = np.unique(pos // frame_len).size

    t_one = best_of(lambda: decode_buffer(data))
    t_stream = best_of(lambda: stream_decode(data, chunk))
    t_noisy = best_of(lambda: stream_decode(noisy_b, chunk))
    line = 921_600 / 10 / frame_len
    print(f"frames: {n:,} x {frame_len} bytes ({len(data) / 1e6:.1f} MB)")
    print(f"one buffer       : {n / t_one:,.0f} frames/s ({len(data) / t_one / 1e6:.0f} MB/s)")
    print(f"256 KiB feeds    : {n / t_stream:,.0f} frames/s")
    print(f"feeds, 1e-4 errs : {n / t_noisy:,.0f} frames/s  (frames hit {hit}, bad counted "
          f"{st.counters.bad_frames + st.counters.truncated_frames})")
    print(f"921.6 kbaud line : {line:,.0f} frames/s -> decoder headroom x{n / t_stream / line:,.0f}")
    print(json.dumps({"mtdata2_frames_decoded_per_s": round(n / t_stream),
                      "mtdata2_frames_decoded_per_s_one_buffer": round(n / t_one),
                      "mtdata2_frames_decoded_per_s_errors_1e-4": round(n / t_noisy),
                      "frame_bytes": frame_len, "line_921k6_frames_per_s": round(line),
                      "headroom_vs_921k6_line_x": round(n / t_stream / line)}))


if __name__ == "__main__":
    main()
