"""Xsens MT protocol: framing, configuration messages, MTData2 codec and the vectorised decoder."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rigctl.drivers import xsens as X
from rigctl.drivers.xsens_decode import RESYNC_RUN, MTData2Stream, decode_buffer

REF_DATA = Path(__file__).resolve().parent / "data"
BASE = [X.XDI.PACKET_COUNTER, X.XDI.SAMPLE_TIME_FINE, X.XDI.ACCELERATION, X.XDI.RATE_OF_TURN,
        X.XDI.TEMPERATURE, X.XDI.STATUS_WORD]


def make_fields(n: int, seed: int = 1, start: int = 0, stf_start: int = 0, stf_step: int = 5) -> dict:
    rng = np.random.default_rng(seed)
    return {"packet_counter": start + np.arange(n), "sample_time_fine": stf_start + stf_step * np.arange(n),
            "acceleration": rng.normal(0, 9.8, (n, 3)), "rate_of_turn": rng.normal(0, 1.0, (n, 3)),
            "temperature": rng.normal(30, 5, n), "status_word": rng.integers(0, 2**32, n),
            "delta_v": rng.normal(0, 0.01, (n, 3)), "delta_q": rng.normal(0, 0.01, (n, 4))}


def frames_bytes(xdis, f) -> tuple[bytes, int]:
    arr = X.encode_mtdata2(xdis, f)
    return arr.tobytes(), arr.shape[1]


# ------------------------------------------------------------------------------- framing

def test_known_constant_messages():
    assert X.go_to_config() == bytes.fromhex("FAFF3000D1")
    assert X.go_to_measurement() == bytes.fromhex("FAFF1000F1")
    assert X.build_message(X.MID.RESET) == bytes.fromhex("FAFF4000C1")
    assert X.error_message(X.ErrorCode.INVALID_MESSAGE) == bytes.fromhex("FAFF420104BA")


@pytest.mark.parametrize("n", [0, 1, 254, 255, 300, 2048])
def test_message_round_trip_including_extended_length(n):
    data = bytes((i * 7) & 0xFF for i in range(n))
    frame = X.build_message(0x42, data)
    if n > 254:
        assert frame[3] == 0xFF and (frame[4] << 8 | frame[5]) == n
    m = X.parse_message(frame)
    assert (m.mid, m.data, m.bid) == (0x42, data, 0xFF)
    bad = bytearray(frame)
    bad[-1] ^= 0x01
    with pytest.raises(X.XsensError, match="checksum"):
        X.parse_message(bytes(bad))


def test_payload_too_long_refused():
    with pytest.raises(X.XsensError):
        X.build_message(0x36, bytes(2049))


def test_output_configuration_round_trip_and_documented_example():
    items = [X.OutputItem(0x1020, 0xFFFF), X.OutputItem(0x1060, 0xFFFF), X.OutputItem(0x4020, 100),
             X.OutputItem(0x8020, 100)]
    payload = X.encode_output_configuration(items)
    assert payload == bytes.fromhex("10 20 FF FF 10 60 FF FF 40 20 00 64 80 20 00 64")
    assert X.decode_output_configuration(payload) == items
    msg = X.parse_message(X.set_output_configuration(items))
    assert msg.mid == X.MID.SET_OUTPUT_CONFIGURATION and msg.data == payload
    with pytest.raises(X.XsensError):
        X.decode_output_configuration(payload[:-1])


def test_split_messages_resyncs_over_garbage_and_keeps_partial():
    a, b = X.ack_for(X.MID.GO_TO_CONFIG), X.error_message(0x21)
    buf = b"\x00\xfa\x12" + a + b"\xfa\xff\x31\x00\x00" + b + b[:3]   # garbage, bad frame, partial
    msgs, used, bad = X.split_messages(buf)
    assert [m.mid for m in msgs] == [0x31, 0x42]
    assert bad == 1
    assert buf[used:] == b[:3]


# ------------------------------------------------------------------------ rate vs baud

def test_rate_check_accepts_fitting_and_refuses_too_fast():
    nbytes = X.mtdata2_frame_bytes(BASE)
    assert nbytes == 5 + 3 * 6 + 2 + 4 + 12 + 12 + 4 + 4
    load = X.check_rate_fits(BASE, 1000, 921_600)
    assert load == pytest.approx(nbytes * 10 * 1000 / 921_600)
    with pytest.raises(X.RateDoesNotFitError, match="921,600 baud"):
        X.check_rate_fits(BASE, 2000, 921_600)
    with pytest.raises(X.RateDoesNotFitError):
        X.check_rate_fits(BASE, 100, 38_400 // 10)


# --------------------------------------------------------------------- MTData2 codec

@pytest.mark.parametrize("prec,tol", [(0, 1e-6), (1, 2**-20), (2, 2**-32), (3, 0.0)])
def test_encode_decode_every_precision(prec, tol):
    n = 50
    f = make_fields(n)
    xdis = BASE + [X.XDI.DELTA_V, X.XDI.DELTA_Q]
    xdis = [x | prec if X.split_xdi(x)[0] in X.XDI_COMPONENTS else x for x in xdis]
    data, _ = frames_bytes(xdis, f)
    batch, c = decode_buffer(data)
    assert c.frames == n and c.bad_frames == 0 and c.garbage_bytes == 0
    for name in ("acceleration", "rate_of_turn", "temperature", "delta_v", "delta_q"):
        got, want = getattr(batch, name), f[name]
        if prec == 0:
            np.testing.assert_array_equal(got, want.astype(np.float32).astype(np.float64))
        else:
            np.testing.assert_allclose(got, want, rtol=0, atol=tol * 1.0001 + 1e-300)
    np.testing.assert_array_equal(batch.counter, np.arange(n))
    np.testing.assert_array_equal(batch.status_word, f["status_word"])
    np.testing.assert_allclose(batch.time_s, f["sample_time_fine"] / 1e4)


def test_byte_errors_1e4_bad_frames_equal_frames_hit():
    n = 100_000
    data, L = frames_bytes(BASE, make_fields(n, seed=3))
    arr = np.frombuffer(data, np.uint8).copy()
    rng = np.random.default_rng(42)
    pos = np.flatnonzero(rng.random(arr.size) < 1e-4)
    pos = pos[(pos >= L) & (pos < arr.size - L)]          # stream already in sync; last frame whole
    arr[pos] ^= rng.integers(1, 256, pos.size).astype(np.uint8)
    hit = np.unique(pos // L)
    assert hit.size > 300
    st = MTData2Stream()
    got = [st.feed(arr[i:i + 8191].tobytes()) for i in range(0, arr.size, 8191)] + [st.flush()]
    counters = np.concatenate([b.counter for b in got])
    c = st.counters
    assert c.bad_frames == hit.size
    assert c.truncated_frames == 0
    assert c.dropped_samples == hit.size
    assert c.frames == n - hit.size
    np.testing.assert_array_equal(counters, np.setdiff1d(np.arange(n), hit))
    offs = np.concatenate([b.offsets for b in got])
    np.testing.assert_array_equal(offs, counters * L)


def test_truncated_frames_counted():
    n = 20
    data, L = frames_bytes(BASE, make_fields(n))
    cut = data[:5 * L] + data[5 * L:5 * L + 17] + data[6 * L:] + data[:10]   # frame 5 cut, tail cut
    st = MTData2Stream()
    b1 = st.feed(cut)
    b2 = st.flush()
    assert len(b1) + len(b2) == n - 1
    assert st.counters.truncated_frames == 2
    assert st.counters.bad_frames == 0
    assert st.counters.dropped_samples == 1


def test_counter_gap_dropped_and_u16_wrap():
    counters = np.r_[65530:65536, 0:4, 7:10]                # wraps, then 3 dropped (4, 5, 6)
    f = make_fields(counters.size)
    f["packet_counter"] = counters
    data, _ = frames_bytes(BASE, f)
    batch, c = decode_buffer(data)
    assert c.dropped_samples == 3
    np.testing.assert_array_equal(batch.counter, np.r_[65530:65540, 65543:65546])


def test_counter_not_advancing_is_rejected_not_accepted():
    f = make_fields(8)
    f["packet_counter"] = np.array([10, 11, 12, 12, 11, 13, 14, 15])
    data, _ = frames_bytes(BASE, f)
    batch, c = decode_buffer(data)
    assert c.out_of_order == 2
    np.testing.assert_array_equal(batch.counter, [10, 11, 12, 13, 14, 15])


def test_counter_restart_resynchronises_after_a_run():
    f = make_fields(10)
    f["packet_counter"] = np.array([500, 501, 502, 0, 1, 2, 3, 4, 5, 6])
    data, _ = frames_bytes(BASE, f)
    batch, c = decode_buffer(data)
    assert c.counter_restarts == 1 and c.out_of_order == 2
    assert len(batch) == 8
    assert np.all(np.diff(batch.counter) == 1)


def test_sample_time_fine_wraps_at_32_bits_across_feeds():
    n = 40
    start = 2**32 - 100
    f = make_fields(n, stf_start=start, stf_step=5)
    data, L = frames_bytes(BASE, f)
    st = MTData2Stream()
    t = np.concatenate([st.feed(data[i:i + 3 * L + 7]).time_s for i in range(0, len(data), 3 * L + 7)])
    np.testing.assert_allclose(t, (start + 5 * np.arange(n)) / 1e4)
    assert np.all(np.diff(t) > 0)


def test_sample_time_fine_one_day_wrap_option():
    day = 864_000_000
    f = make_fields(6, stf_start=day - 10, stf_step=5)
    f["sample_time_fine"] = f["sample_time_fine"] % day
    data, _ = frames_bytes(BASE, f)
    batch, _ = decode_buffer(data, wrap_ticks=day)
    np.testing.assert_array_equal(batch.sample_time_fine, day - 10 + 5 * np.arange(6))


def _real_session(start_ticks: int) -> tuple[dict, np.ndarray]:
    """imu_tk's real Xsens MTi session (tests/data/imutk-xsens: 51,175 samples, 512 s, its
    timestamps jittering 9.0-10.4 ms) as MTData2 fields: PacketCounter the sample index,
    SampleTimeFine the time column in 10 kHz ticks from ``start_ticks`` (mod 2^32 on the wire),
    acceleration and rate of turn from the raw counts at the MTi's nominal scales. Returns the
    fields and the true unwrapped ticks."""
    d = REF_DATA / "imutk-xsens"
    acc, gyr = np.loadtxt(d / "xsens_acc.mat.gz"), np.loadtxt(d / "xsens_gyro.mat.gz")
    n = len(acc)
    ticks = start_ticks + np.rint((acc[:, 0] - acc[0, 0]) * 1e4).astype(np.int64)
    f = make_fields(n)
    f.update(packet_counter=np.arange(n), sample_time_fine=ticks % 2**32,
             acceleration=(acc[:, 1:] - 32768) / 415.0, rate_of_turn=(gyr[:, 1:] - 32768) / 4770.0)
    return f, ticks


def _set_stf_bit(arr: np.ndarray, k: int, bit: int) -> None:
    """Frame k's SampleTimeFine with ``bit`` set (it was clear), the checksum made to pass again:
    a corruption the checksum does not catch."""
    assert tuple(arr[k, 9:12]) == (X.XDI.SAMPLE_TIME_FINE >> 8, X.XDI.SAMPLE_TIME_FINE & 0xFF, 4)
    byte, mask = 12 + 3 - bit // 8, 1 << (bit % 8)
    assert not arr[k, byte] & mask
    arr[k, byte] |= mask
    arr[k, -1] = (-int(arr[k, 1:-1].sum(dtype=np.int64))) & 0xFF


def test_a_corrupted_sample_time_fine_is_rejected_and_never_shifts_the_rest():
    """Real frames (imu_tk's MTi session), SampleTimeFine starting 20 s before its 2^32 wrap.
    Three frames carry a corrupted time that passes the checksum: +2^20 ticks (105 s ahead: the
    next true one would read as a wrap), the top bit (2^31: ahead by more than half the wrap),
    and +2^22 on the last frame of one feed (the next true one comes in the next feed). Each is
    kept without a time and counted; every other frame keeps its true time (before the fix every
    sample after the first one came 2^32 ticks, 4.97 days, late)."""
    f, ticks = _real_session(2**32 - 200_000)
    data, L = frames_bytes(BASE, f)
    arr = np.frombuffer(data, np.uint8).reshape(-1, L).copy()
    n = len(arr)
    chunk = 997
    bad = {12_000: 20, 30_000: 31, 5 * chunk - 1: 22}
    for k, bit in bad.items():
        assert not (int(f["sample_time_fine"][k]) >> bit) & 1
        _set_stf_bit(arr, k, bit)
    st = MTData2Stream()
    got = [st.feed(arr[i:i + chunk].tobytes()) for i in range(0, n, chunk)] + [st.flush()]
    stf = np.concatenate([b.sample_time_fine for b in got])
    t = np.concatenate([b.time_s for b in got])
    c = st.counters
    assert c.frames == n and c.bad_frames == 0 and c.time_outliers == 3 and c.time_restarts == 0
    np.testing.assert_array_equal(np.concatenate([b.counter for b in got]), np.arange(n))
    flagged = np.flatnonzero(stf < 0)
    np.testing.assert_array_equal(flagged, sorted(bad))
    assert np.isnan(t[flagged]).all()
    good = np.setdiff1d(np.arange(n), flagged)
    np.testing.assert_array_equal(stf[good], ticks[good])       # past the true wrap too
    np.testing.assert_array_equal(t[good], ticks[good] / 1e4)
    assert ticks[-1] > 2**32 and np.all(np.diff(t[good]) > 0)
    np.testing.assert_array_equal(np.concatenate([b.acceleration for b in got]),
                                  f["acceleration"].astype(np.float32).astype(np.float64))


def test_a_restarted_sample_time_fine_is_a_new_time_base_not_an_outlier_each_frame():
    """The MTi restarts mid-session (PacketCounter and SampleTimeFine from 0): after the
    counter's resynchronisation the first stamp of the new time base is left without a time, the
    second continues it and is taken (counted as a restart, not as an outlier; unwrapped as the
    old decoder did, as a wrap), and the later ones follow it one true step each."""
    f, ticks = _real_session(50_000_000)
    k = 2000
    f["packet_counter"][k:] -= k
    f["sample_time_fine"][k:] = ticks[k:] - ticks[k]
    data, _ = frames_bytes(BASE, {key: v[:4000] for key, v in f.items()})
    batch, c = decode_buffer(data)
    assert c.counter_restarts == 1 and c.out_of_order == RESYNC_RUN - 1
    assert c.time_restarts == 1 and c.time_outliers == 0
    stf = batch.sample_time_fine
    np.testing.assert_array_equal(stf[:k], ticks[:k])
    first = k + RESYNC_RUN - 1                  # the counter's first frame after its resync
    assert stf[k] == -1 and np.all(stf[k + 1:] >= 0)
    np.testing.assert_array_equal(np.diff(stf[k + 1:]), np.diff(ticks[first + 1:4000]))
    assert stf[k + 1] == ticks[k - 1] + (ticks[first + 1] - ticks[k] - ticks[k - 1]) % 2**32


def test_unknown_data_id_counted_known_items_kept():
    n = 10
    f = make_fields(n)
    data, L = frames_bytes(BASE, f)
    arr = np.frombuffer(data, np.uint8).reshape(n, L).copy()
    # turn the Temperature item (XDI 0x0810, 4 bytes) into an unknown XDI 0x0A10 of the same size
    off = 4 + 3 * 4 + 2 + 4 + 12 + 12
    assert arr[0, off] == 0x08 and arr[0, off + 1] == 0x10
    arr[:, off] = 0x0A
    arr[:, -1] = (-arr[:, 1:-1].sum(axis=1).astype(np.int64)) & 0xFF
    batch, c = decode_buffer(arr.tobytes())
    assert c.unknown_xdi == {0x0A10: n}
    assert len(batch) == n and np.all(np.isnan(batch.temperature))
    np.testing.assert_array_equal(batch.acceleration, f["acceleration"].astype(np.float32))


def test_malformed_structure_with_valid_checksum_not_accepted():
    f = make_fields(3)
    data, L = frames_bytes(BASE, f)
    arr = np.frombuffer(data, np.uint8).reshape(3, L).copy()
    arr[1, 4 + 2] = 3                      # PacketCounter item claims 3 bytes: items no longer tile
    arr[1, -1] = (-int(arr[1, 1:-1].sum())) & 0xFF
    batch, c = decode_buffer(arr.tobytes())
    assert c.malformed_frames == 1 and c.bad_frames == 1
    np.testing.assert_array_equal(batch.counter, [0, 2])


def test_irregular_layouts_and_control_messages_interleaved():
    f = make_fields(6)
    parts = [X.encode_mtdata2(BASE, {k: v[:2] for k, v in f.items()}).tobytes(),
             X.ack_for(X.MID.GO_TO_MEASUREMENT),
             X.encode_mtdata2(BASE[:3], {k: v[2:4] for k, v in f.items()}).tobytes(),
             X.encode_mtdata2(BASE + [X.XDI.DELTA_Q], {k: v[4:] for k, v in f.items()}).tobytes()]
    batch, c = decode_buffer(b"".join(parts))
    assert c.bad_frames == 0 and c.messages == 1
    assert [m.mid for m in batch.messages] == [X.MID.GO_TO_MEASUREMENT_ACK]
    np.testing.assert_array_equal(batch.counter, np.arange(6))
    assert np.all(np.isnan(batch.rate_of_turn[2:4])) and not np.isnan(batch.rate_of_turn[[0, 1, 4, 5]]).any()
    assert np.isnan(batch.delta_q[:4]).all() and not np.isnan(batch.delta_q[4:]).any()


def test_joining_a_running_stream_is_presync_not_bad():
    data, L = frames_bytes(BASE, make_fields(10))
    batch, c = decode_buffer(data[L // 2:])
    assert len(batch) == 9 and c.bad_frames == 0 and c.presync_bytes == L - L // 2


def _checksum_ok(buf: bytes, off: int) -> bool:
    ln = buf[off + 3]
    hdr = 4
    if ln == 0xFF:
        ln, hdr = (buf[off + 4] << 8) | buf[off + 5], 6
    return sum(buf[off + 1:off + hdr + ln + 1]) % 256 == 0


@settings(max_examples=150, deadline=None, derandomize=True, database=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.one_of(st.binary(max_size=80), st.integers(0, 3)), max_size=25),
       st.integers(1, 97), st.integers(0, 255))
def test_fuzz_random_bytes_never_crash_never_bad_checksum(pieces, chunk, flip):
    frames = X.encode_mtdata2(BASE, make_fields(4, seed=flip)).tobytes()
    L = len(frames) // 4
    buf = bytearray()
    for p in pieces:
        if isinstance(p, int):
            fr = bytearray(frames[p * L:(p + 1) * L])
            if flip % 3 == 0:
                fr[flip % L] ^= 0x5A
            buf += fr
        else:
            buf += p
    data = bytes(buf)
    s = MTData2Stream()
    out = [s.feed(data[i:i + chunk]) for i in range(0, len(data), chunk)] + [s.flush()]
    for b in out:
        for off in b.offsets.tolist():
            assert data[off:off + 3] == b"\xfa\xff\x36"
            assert _checksum_ok(data, off)
        for m in b.messages:
            assert X.build_message(m.mid, m.data, m.bid) in data
        assert np.all(np.diff(b.counter) > 0)
    c = s.counters
    assert c.garbage_bytes + c.presync_bytes <= len(data)


def test_a_time_base_that_jumps_ahead_is_no_device_restart():
    """A device restart (``device_restarts``, on which a run warms the IMU up again) is a new
    time base that began behind the last stamp (the restart above: SampleTimeFine from 0); one
    that jumped ahead -- 5 s of SampleTimeFine over a single PacketCounter step, as after a slow
    reconfiguration (the MTi's time runs on in config mode, its counter does not) -- is a new
    time base too (``time_restarts``), not a restart of the unit."""
    f, ticks = _real_session(50_000_000)
    k = 2000
    f["sample_time_fine"][k:] = ticks[k:] + 50_000
    data, _ = frames_bytes(BASE, {key: v[:4000] for key, v in f.items()})
    _, c = decode_buffer(data)
    assert c.time_restarts == 1 and c.device_restarts == 0
    f, ticks = _real_session(50_000_000)
    f["packet_counter"][k:] -= k
    f["sample_time_fine"][k:] = ticks[k:] - ticks[k]
    data, _ = frames_bytes(BASE, {key: v[:4000] for key, v in f.items()})
    _, c = decode_buffer(data)
    assert c.time_restarts == 1 and c.device_restarts == 1
