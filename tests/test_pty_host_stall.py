"""The emulated IMU port's flow control (sim/links.py FlowPtyEndpoint) tells a client that stopped
reading from a host that stopped moving bytes.

Under load (17-26 on 2 cores) the pty master of the emulated Xsens found no room for over 1.5 s
(its write_timeout_s) while the driver's reader thread waited in select() with nothing to read:
the slave's input queue was empty at every sample. The port counted that as the client's silence
and dropped the rest of the batch: a counter gap inside one read, which paused
tests/test_daemon_wire.py's ten-link-drop run on 'imu-gap' with nothing in the record to
explain it. Here the host's stall is made deterministic: output on the pty master is suspended
(tcflow TCOOFF: the master has no room, the client's queue stays empty) for longer than the
wait, then resumed. A client that stops reading still loses bytes after the wait, as before.

Real ptys, a raw client fd reading as a driver's reader thread does; ~5 s.
"""
from __future__ import annotations

import os
import select
import termios
import threading
import time

from rigctl.sim.links import FlowPtyEndpoint

PAYLOAD = bytes(range(256)) * 1024          # 256 kB: more than the pty holds (~68 kB)
STALL_S = 1.5 * FlowPtyEndpoint.write_timeout_s


def _client(path: str) -> int:
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    os.write(fd, b"\x00")                    # the client speaks first (as a driver's GoToConfig)
    return fd


def _read_for(fd: int, seconds: float, out: bytearray, stop: threading.Event | None = None) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end and not (stop is not None and stop.is_set()):
        r, _, _ = select.select([fd], [], [], 0.01)
        if r:
            out += os.read(fd, 1 << 16)


def _wait_spoken(ep: FlowPtyEndpoint) -> None:
    end = time.monotonic() + 10.0
    while ep.received_bytes == 0:
        assert time.monotonic() < end, "the port never saw its client speak"
        time.sleep(0.005)


def test_a_port_that_moves_no_bytes_while_its_client_waits_loses_nothing():
    """The master takes no byte for 2.25 s (1.5x the 1.5 s wait) while the client reads all it is
    given: the write waits it out and every byte arrives, in order. Before, the write gave up
    after 1.5 s and dropped the rest of the 256 kB (overflow_bytes > 0)."""
    ep = FlowPtyEndpoint(name="stall-pty")
    fd = _client(ep.path)
    got, done = bytearray(), threading.Event()
    try:
        _wait_spoken(ep)
        reader = threading.Thread(target=_read_for, args=(fd, 60.0, got, done), daemon=True)
        reader.start()
        termios.tcflow(ep.master, termios.TCOOFF)        # the host moves no bytes
        resume = threading.Timer(STALL_S, termios.tcflow, (ep.master, termios.TCOON))
        resume.start()
        t0 = time.monotonic()
        sent = ep.write(PAYLOAD)
        took = time.monotonic() - t0
        resume.join()
        end = time.monotonic() + 10.0
        while len(got) < sent and time.monotonic() < end:
            time.sleep(0.01)
        done.set()
        reader.join()
    finally:
        os.close(fd)
        ep.close()
    assert took >= STALL_S - 0.05, f"the write returned after {took:.2f} s, inside the stall"
    assert ep.overflow_bytes == 0 and sent == len(PAYLOAD), \
        f"{ep.overflow_bytes} bytes dropped while the client waited for them"
    assert bytes(got) == PAYLOAD
    assert ep.host_waits == 1


def test_a_client_that_stops_reading_still_loses_bytes_after_the_wait():
    """The client reads nothing: its queue stays full, the write gives up after write_timeout_s
    and drops the rest (a client that went away cannot stall the emulator)."""
    ep = FlowPtyEndpoint(name="silent-pty")
    fd = _client(ep.path)
    try:
        _wait_spoken(ep)
        t0 = time.monotonic()
        sent = ep.write(PAYLOAD)
        took = time.monotonic() - t0
    finally:
        os.close(fd)
        ep.close()
    assert 0 < sent < len(PAYLOAD) and ep.overflow_bytes == len(PAYLOAD) - sent
    assert FlowPtyEndpoint.write_timeout_s - 0.05 <= took < FlowPtyEndpoint.write_timeout_s + 1.0, took
    assert ep.host_waits == 0
