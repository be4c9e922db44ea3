"""Decode throughput of the vectorised decoders: Xsens MTData2 (rigctl.drivers.xsens_decode),
VectorNav binary (rigctl.drivers.vectornav) and the declarative frame (rigctl.drivers.frame_decl).

VectorNav frames: group 1 TimeStartup + SyncInCnt, group 3 UncompAccel + UncompGyro + Temp (the
driver's layout), 46 bytes, CRC-16. Declarative frames: the docs/hardware.md example (sync AA 55,
length, counter, time, 6 x i32, temperature, status, CRC-16/CCITT), 38 bytes. Each: one buffer,
256 KiB feeds, feeds with byte errors at 1e-4 (frames hit vs bad frames counted). Target for
both: >= 1e6 frames/s in 256 KiB feeds.

Frames: PacketCounter, SampleTimeFine, Acceleration, RateOfTurn, Temperature, StatusWord
(float32), 61 bytes each. Measures frames decoded per second (a) from one large buffer,
(b) streaming in 256 KiB feeds, (c) streaming with byte errors at 1e-4. For scale, a 921.6 kbaud
8N1 line carries 921600 / 10 / 61 = 1,511 such frames per second (about 2,300 for a 40-byte frame).
Target: >= 1e6 frames/s. Last line: one JSON object.

Recording CPU share (``--record-seconds``, default 60): the emulated Xsens (``rigctl sim up`` in a
separate process, 1x real time, 2 kHz, 4 Mbaud nominal) streams over a pty; this process runs the
Xsens driver (reader thread + decoder) and the HDF5 recorder, polled every 50 ms as the engine
does. CPU share = (user + system CPU time of this process, resource.getrusage) / wall time, in
% of one core; zero drops = no bad/truncated frames, no PacketCounter gaps, no counter gaps in
the recording, no bytes dropped by the emulator's pty. Target: < 10 % of one core.

Usage: python benchmarks/decode.py [n_frames] [--record-seconds S]   (S = 0 skips the recording)
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json  # noqa: E402
import resource  # noqa: E402
import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import yaml  # noqa: E402

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


def other_decoders(n: int, chunk: int) -> dict:
    """VectorNav and declarative-frame throughput (frames/s) and error counting at 1e-4."""
    from rigctl.drivers import frame_decl
    from rigctl.drivers import vectornav as V
    from rigctl.drivers.vectornav_imu import LAYOUT
    from rigctl.config.frame_spec import parse_frame_spec
    from rigctl.sim.frame_server import EXAMPLE
    from rigctl.yamlio import LocDict

    rng = np.random.default_rng(2)
    acc, gyr, temp = rng.normal(0, 9.8, (n, 3)), rng.normal(0, 1, (n, 3)), rng.normal(30, 1, n)
    vn = V.encode(LAYOUT, {"time_startup_ns": 10**9 + 1_250_000 * np.arange(n), "syncin_count": np.arange(n) // 800,
                           "uncomp_accel": acc, "uncomp_gyro": gyr, "temperature": temp}).tobytes()
    spec = parse_frame_spec(LocDict({"frame": EXAMPLE}))
    fr = frame_decl.encode_binary(spec, {"counter": np.arange(n), "time": 1250 * np.arange(n),
                                         **{f"accel_{a}": acc[:, j] for j, a in enumerate("xyz")},
                                         **{f"gyro_{a}": gyr[:, j] for j, a in enumerate("xyz")},
                                         "temperature": temp}).tobytes()
    out = {}
    for name, data, make, length in (("vectornav", vn, lambda: V.decoder(LAYOUT), LAYOUT.length),
                                     ("frame_decl", fr, lambda: frame_decl.binary_decoder(spec), spec.length)):
        def feed(buf, make=make):
            st = make()
            view = memoryview(buf)
            for i in range(0, len(buf), chunk):
                st.feed(np.frombuffer(view[i:i + chunk], np.uint8))
            st.flush()
            return st

        def one(buf=data, make=make):
            st = make()
            st.feed(buf, final=True)
            return st

        assert one().counters.frames == n
        noisy = np.frombuffer(data, np.uint8).copy()
        pos = np.flatnonzero(rng.random(noisy.size) < 1e-4)
        noisy[pos] ^= rng.integers(1, 256, pos.size).astype(np.uint8)
        noisy_b = noisy.tobytes()
        st = feed(noisy_b)
        hit = int(np.unique(pos // length).size)
        counted = st.counters.bad_frames + st.counters.truncated_frames
        t_one, t_stream, t_noisy = best_of(one), best_of(lambda: feed(data)), best_of(lambda: feed(noisy_b))
        print(f"{name:<10s} {length} bytes: one buffer {n / t_one:,.0f} frames/s, 256 KiB feeds {n / t_stream:,.0f} "
              f"frames/s, 1e-4 errors {n / t_noisy:,.0f} frames/s (frames hit {hit}, bad counted {counted})")
        out.update({f"{name}_frames_decoded_per_s": round(n / t_stream),
                    f"{name}_frames_decoded_per_s_one_buffer": round(n / t_one),
                    f"{name}_frames_decoded_per_s_errors_1e-4": round(n / t_noisy),
                    f"{name}_frame_bytes": length, f"{name}_frames_hit_1e-4": hit,
                    f"{name}_bad_frames_counted_1e-4": counted})
    return out


def record_cpu_share(seconds: float, rate_hz: int = 2000) -> dict:
    """Record a 2 kHz stream from an emulator process for ``seconds``; CPU share of this process."""
    import h5py

    from rigctl.clock import RealClock
    from rigctl.drivers.xsens_imu import XsensImu
    from rigctl.recording.recorder import Recorder

    root = Path(__file__).resolve().parent.parent
    tmp = Path(tempfile.mkdtemp(prefix="rigctl-bench-"))
    cfg = yaml.safe_load((root / "configs" / "sim.yaml").read_text())
    cfg["imu"]["rate_hz"] = rate_hz
    (tmp / "physics.yaml").write_text(yaml.safe_dump(cfg))
    emu = subprocess.Popen([sys.executable, "-m", "rigctl.cli", "sim", "up", "--config", str(tmp / "physics.yaml"),
                            "--speed", "1", "--imu-baudrate", "4000000", "--link-dir", str(tmp / "ports")],
                           cwd=root, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                           env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        while (line := emu.stdout.readline()) and line.strip() != "ready":
            pass
        imu = XsensImu(str(tmp / "ports" / "imu"), rate_hz, RealClock(), baudrate=4_000_000)
        imu.connect()
        rec = Recorder(tmp / "rec.h5", {"procedure_name": "benchmark"}, None, imu_rate_hz=rate_hz)
        ru0, w0 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
        while time.monotonic() - w0 < seconds:
            time.sleep(0.05)
            rec.append_imu(imu.read())
        wall = time.monotonic() - w0
        ru1 = resource.getrusage(resource.RUSAGE_SELF)
        rec.close("complete")
        c = imu.counters
        imu.close()
    finally:
        emu.send_signal(signal.SIGINT)
        emu.communicate(timeout=30)
    with h5py.File(tmp / "rec.h5", "r") as f:
        counter = f["imu/counter"][()].astype(np.int64)
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    gaps = int(np.count_nonzero(np.diff(counter) != 1))
    lost = c["bad_frames"] + c["truncated_frames"] + c["dropped_samples"] + gaps
    return {"record_seconds": round(wall, 1), "samples": int(counter.size), "cpu_s": round(cpu, 2),
            "cpu_share_pct": round(100 * cpu / wall, 2), "lost": lost}


def main() -> None:
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    record_s = 60.0
    if "--record-seconds" in sys.argv:
        record_s = float(sys.argv[sys.argv.index("--record-seconds") + 1])
        args = [a for a in args if a != sys.argv[sys.argv.index("--record-seconds") + 1]]
    n = int(args[0]) if args else 1_000_000
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
    figures = {"mtdata2_frames_decoded_per_s": round(n / t_stream),
               "mtdata2_frames_decoded_per_s_one_buffer": round(n / t_one),
               "mtdata2_frames_decoded_per_s_errors_1e-4": round(n / t_noisy),
               "frame_bytes": frame_len, "line_921k6_frames_per_s": round(line),
               "headroom_vs_921k6_line_x": round(n / t_stream / line)}
    figures.update(other_decoders(n, chunk))
    if record_s > 0:
        r = record_cpu_share(record_s)
        print(f"recording 2 kHz over a pty: {r['samples']:,} samples in {r['record_seconds']} s, "
              f"CPU {r['cpu_s']} s = {r['cpu_share_pct']} % of one core, lost samples/frames {r['lost']}")
        figures.update({"record_2khz_pty_cpu_pct_of_core": r["cpu_share_pct"],
                        "record_2khz_pty_seconds": r["record_seconds"], "record_2khz_pty_samples": r["samples"],
                        "record_2khz_pty_lost_samples": r["lost"]})
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
