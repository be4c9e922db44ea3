"""The streaming IMU drivers' counters are one consistent snapshot with what ``read`` returns.

The reader thread decodes a chunk (which counts its frames) and stores it (which makes them
readable). Before the fix a reader thread descheduled between the two let a caller see ~800
frames counted that ``read`` did not return (the official CI's failure of
test_imu_byte_errors_1e6_frames_through_the_driver: 1020222 rows for 1021064 frames).

Here the decoder is made to stop right after decoding, as a descheduled thread would, and the
test asks for the counters and reads from another thread meanwhile. No port, no emulator; the
frames are encoded in the test.
"""
from __future__ import annotations

import threading

import numpy as np
import pytest

from rigctl.drivers import frame_decl
from rigctl.drivers.frame_imu import FrameImu
from rigctl.drivers.xsens import SAMPLE_TIME_FINE_HZ, encode_mtdata2
from rigctl.drivers.xsens_imu import XsensImu
from rigctl.config.frame_spec import parse_frame_spec
from rigctl.sim.frame_server import EXAMPLE
from rigctl.yamlio import LocDict

RATE = 100
N = 50


class HandClock:
    speed = 1.0

    def __init__(self, t: float) -> None:
        self.t = t

    def now(self) -> float:
        return self.t


def _frame_imu(tmp_path):
    spec = parse_frame_spec(LocDict({"frame": EXAMPLE}))
    imu = FrameImu(str(tmp_path / "no-port"), spec, RATE, HandClock(10.0), align_wait_s=0.0)
    k = np.arange(N)
    v = {"counter": k, "time": np.rint(k / RATE / 1e-6).astype(np.int64),
         **{f"{q}_{a}": np.zeros(N) for q in ("accel", "gyro") for a in "xyz"}, "temperature": np.full(N, 25.0)}
    return imu, frame_decl.encode_binary(spec, v).tobytes()


def _xsens_imu(tmp_path):
    imu = XsensImu(str(tmp_path / "no-port"), RATE, HandClock(10.0), align_wait_s=0.0)
    k = np.arange(N)
    f = {"packet_counter": k, "sample_time_fine": k * (SAMPLE_TIME_FINE_HZ // RATE),
         "status_word": np.zeros(N, np.int64), "acceleration": np.zeros((N, 3)),
         "rate_of_turn": np.zeros((N, 3)), "delta_v": np.zeros((N, 3)), "delta_q": np.tile([1.0, 0, 0, 0], (N, 1)),
         "temperature": np.full(N, 25.0)}
    return imu, encode_mtdata2([it.xdi for it in imu.items], f).tobytes()


@pytest.mark.parametrize("make", [_frame_imu, _xsens_imu], ids=["frame", "xsens"])
def test_counters_never_count_a_frame_that_read_cannot_return(tmp_path, make) -> None:
    imu, data = make(tmp_path)
    imu.offset = -0.5                       # configured: device time + offset, all before the clock
    decoded, release = threading.Event(), threading.Event()
    feed = imu.stream.feed

    def stalled_feed(chunk: bytes):
        out = feed(chunk)                   # the frames are counted here ...
        decoded.set()
        release.wait(10.0)                  # ... and the thread is descheduled before storing them
        return out

    imu.stream.feed = stalled_feed
    reader = threading.Thread(target=imu._feed, args=(data,))
    reader.start()
    assert decoded.wait(10.0)
    seen: dict = {}

    def caller() -> None:                   # what test_imu_byte_errors does: counters, then read
        seen["counters"] = imu.counters
        seen["rows"] = len(imu.read())

    t = threading.Thread(target=caller)
    t.start()
    t.join(0.3)                             # the caller may (fixed) or may not (broken) wait for the store
    release.set()
    t.join(10.0)
    reader.join(10.0)
    assert not t.is_alive() and not reader.is_alive()
    c = seen["counters"]
    assert c["frames"] == N
    # every frame the snapshot counts is handed out by the read that follows it
    assert seen["rows"] == c["frames"] - c["incomplete_frames"] - c["restamp_dropped"]
