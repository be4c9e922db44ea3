"""Emulated Xsens MTi on a real pty, driven by a pyserial client."""
from __future__ import annotations

import time

import numpy as np
import pytest
import serial

from rigctl.drivers import xsens as X
from rigctl.drivers.xsens_decode import MTData2Stream
from rigctl.sim.xsens_server import XsensServer, still_source

BASE = [X.XDI.PACKET_COUNTER, X.XDI.SAMPLE_TIME_FINE, X.XDI.ACCELERATION, X.XDI.RATE_OF_TURN,
        X.XDI.TEMPERATURE, X.XDI.STATUS_WORD]


def request(port, msg: bytes, want_mid: int, timeout: float = 3.0) -> X.Message:
    """Send ``msg`` and return the first reply with ``want_mid`` or an Error message."""
    port.write(msg)
    buf, t_end = b"", time.monotonic() + timeout
    while time.monotonic() < t_end:
        buf += port.read(port.in_waiting or 1)
        msgs, used, _ = X.split_messages(buf)
        buf = buf[used:]
        for m in msgs:
            if m.mid in (want_mid, X.MID.ERROR):
                return m
    raise TimeoutError(f"no reply 0x{want_mid:02X}")


@pytest.fixture
def fast_server():
    t0 = time.monotonic()
    srv = XsensServer(clock=lambda: 20.0 * (time.monotonic() - t0), baudrate=921_600)
    yield srv
    srv.close()


@pytest.fixture
def client(fast_server):
    port = serial.serial_for_url(fast_server.path, baudrate=921_600, timeout=0.05)
    yield port
    port.close()


def test_config_measurement_cycle_and_stream_decodes(fast_server, client):
    assert request(client, X.go_to_config(), X.MID.GO_TO_CONFIG_ACK).mid == X.MID.GO_TO_CONFIG_ACK
    items = [X.OutputItem(x, 200) for x in BASE]
    ack = request(client, X.set_output_configuration(items), X.MID.SET_OUTPUT_CONFIGURATION_ACK)
    assert ack.mid == X.MID.SET_OUTPUT_CONFIGURATION_ACK
    assert X.decode_output_configuration(ack.data) == items
    dec = MTData2Stream()
    client.write(X.go_to_measurement())
    batches, t_end = [], time.monotonic() + 0.4
    while time.monotonic() < t_end:
        batches.append(dec.feed(client.read(4096)))
    client.write(X.go_to_config())             # the ack arrives inside the stream: decode it there
    t_end = time.monotonic() + 3
    while time.monotonic() < t_end and not any(m.mid == X.MID.GO_TO_CONFIG_ACK for m in batches[-1].messages):
        batches.append(dec.feed(client.read(4096)))
    time.sleep(0.05)
    batches.append(dec.feed(client.read(65536)))
    batches.append(dec.flush())
    assert any(m.mid == X.MID.GO_TO_CONFIG_ACK for b in batches for m in b.messages)
    cnt = np.concatenate([b.counter for b in batches])
    acc = np.concatenate([b.acceleration for b in batches])
    t = np.concatenate([b.time_s for b in batches])
    assert cnt.size > 200                                   # 200 Hz x 20x speed x 0.4 s = 1600 nominal
    np.testing.assert_array_equal(cnt, np.arange(cnt.size))
    np.testing.assert_allclose(np.diff(t), 1 / 200, atol=1e-4)  # SampleTimeFine: 10 kHz ticks
    np.testing.assert_array_equal(acc, np.tile(np.float32([0, 0, 9.80665]), (cnt.size, 1)))
    c = dec.counters
    assert (c.bad_frames, c.truncated_frames, c.dropped_samples) == (0, 0, 0)
    assert fast_server.port.overflow_bytes == 0


def test_rate_that_does_not_fit_the_baud_rate_is_refused(fast_server, client):
    items = [X.OutputItem(x, 2000) for x in BASE]
    with pytest.raises(X.RateDoesNotFitError):
        X.check_rate_fits(BASE, 2000, 921_600)
    request(client, X.go_to_config(), X.MID.GO_TO_CONFIG_ACK)
    reply = request(client, X.set_output_configuration(items), X.MID.SET_OUTPUT_CONFIGURATION_ACK)
    assert reply.mid == X.MID.ERROR and reply.data == bytes([X.ErrorCode.INVALID_PARAMETER])
    assert "baud" in fast_server.last_error
    assert fast_server.rate_hz == 100                        # previous configuration kept


def test_config_refused_in_measurement_and_unknown_message(fast_server, client):
    request(client, X.go_to_measurement(), X.MID.GO_TO_MEASUREMENT_ACK)
    reply = request(client, X.set_output_configuration([X.OutputItem(X.XDI.ACCELERATION, 100)]),
                    X.MID.SET_OUTPUT_CONFIGURATION_ACK)
    assert reply.mid == X.MID.ERROR and reply.data == bytes([X.ErrorCode.INVALID_MESSAGE])
    request(client, X.go_to_config(), X.MID.GO_TO_CONFIG_ACK)
    assert request(client, X.build_message(0x77), 0x78).mid == X.MID.ERROR
    did = request(client, X.build_message(X.MID.REQ_DID), X.MID.DEVICE_ID)
    assert did.data == (0x03780001).to_bytes(4, "big")


def test_injected_byte_errors_counted_exactly():
    t0 = time.monotonic()
    srv = XsensServer(clock=lambda: 20.0 * (time.monotonic() - t0), byte_error_rate=2e-3, seed=7,
                      source=still_source)
    port = serial.serial_for_url(srv.path, baudrate=921_600, timeout=0.05)
    try:
        request(port, X.go_to_config(), X.MID.GO_TO_CONFIG_ACK)
        dec = MTData2Stream()
        port.write(X.go_to_measurement())
        t_end = time.monotonic() + 0.5
        while time.monotonic() < t_end:
            dec.feed(port.read(4096))
        port.write(X.go_to_config())
        time.sleep(0.1)
        dec.feed(port.read(1 << 20))
        dec.flush()
    finally:
        port.close()
        srv.close()
    c = dec.counters
    assert srv.frames_hit > 10
    assert c.bad_frames + c.truncated_frames == srv.frames_hit
    assert c.frames + srv.frames_hit == srv.frames_sent


def test_mixed_item_rates_give_irregular_layouts_that_decode(fast_server, client):
    items = [X.OutputItem(X.XDI.PACKET_COUNTER), X.OutputItem(X.XDI.SAMPLE_TIME_FINE),
             X.OutputItem(X.XDI.ACCELERATION, 200), X.OutputItem(X.XDI.TEMPERATURE, 50)]
    request(client, X.go_to_config(), X.MID.GO_TO_CONFIG_ACK)
    assert request(client, X.set_output_configuration(items), X.MID.SET_OUTPUT_CONFIGURATION_ACK).mid == \
        X.MID.SET_OUTPUT_CONFIGURATION_ACK
    dec = MTData2Stream()
    client.write(X.go_to_measurement())
    batches, t_end = [], time.monotonic() + 0.3
    while time.monotonic() < t_end:
        batches.append(dec.feed(client.read(4096)))
    temp = np.concatenate([b.temperature for b in batches])
    cnt = np.concatenate([b.counter for b in batches])
    assert cnt.size > 40 and dec.counters.bad_frames == 0
    np.testing.assert_array_equal(np.flatnonzero(~np.isnan(temp)), np.arange(0, cnt.size, 4))
