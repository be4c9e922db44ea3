"""Byte-stream plumbing for the emulated hardware: raw ptys, a pty null-modem bridge, TCP.

- :class:`PtyEndpoint`: the server keeps the pty master; clients open ``endpoint.path``
  (``/dev/pts/N``) with ``serial.serial_for_url``. The server also keeps the slave open so a
  client closing and reopening the port never makes the master read EIO. Output is written
  non-blocking: if no one drains the port, bytes are dropped and counted (``overflow_bytes``),
  like a UART with nobody listening, instead of stalling the emulator.
- :class:`FlowPtyEndpoint`: a :class:`PtyEndpoint` whose writes wait for a client that drains
  the port (flow control, for emulators faster than the baud rate), and
  :class:`FreeRunPtyEndpoint`, the same for a device that never hears from its client.
- :class:`PtyBridge`: two ptys joined master-to-master (a null-modem cable) for servers that
  want to open a port path themselves (pymodbus RTU): ``bridge.path_a`` <-> ``bridge.path_b``.
- :class:`TcpEndpoint`: a listening socket on 127.0.0.1 (port 0 = OS-picked), one thread and one
  handler (from ``make_handler()``) per connection.

All of them deliver received bytes to ``on_data(data: bytes, write: Callable[[bytes], None])``
from a reader thread and are torn down by ``close()`` (idempotent; joins the threads).
"""
from __future__ import annotations

import errno
import fcntl
import logging
import os
import select
import socket
import struct
import termios
import threading
import time
import tty
from collections.abc import Callable

log = logging.getLogger(__name__)
OnData = Callable[[bytes, Callable[[bytes], None]], None]


def open_raw_pty() -> tuple[int, int, str]:
    """(master_fd, slave_fd, slave_path) with the slave in raw mode (no echo, no line editing)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    return master, slave, os.ttyname(slave)


class PtyEndpoint:
    """Server side of a pty; ``path`` is what the client opens."""

    def __init__(self, on_data: OnData | None = None, name: str = "pty") -> None:
        self.master, self._slave, self.path = open_raw_pty()
        os.set_blocking(self.master, False)
        self.on_data = on_data
        self.overflow_bytes = 0
        #: bytes the client has written into the port (it has it open and talks to the device)
        self.received_bytes = 0
        self._wlock = threading.Lock()
        self._stop_r, self._stop_w = os.pipe()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=f"{name}-reader", daemon=True)
        self._thread.start()

    def write(self, data: bytes) -> int:
        """Write without blocking; bytes that do not fit the pty buffer are dropped and counted."""
        with self._wlock:
            if self._closed:
                return 0
            view, sent = memoryview(data), 0
            while sent < len(view):
                try:
                    sent += os.write(self.master, view[sent:])
                except BlockingIOError:
                    break
                except OSError as exc:
                    if exc.errno in (errno.EIO, errno.EBADF):
                        break
                    raise
            self.overflow_bytes += len(view) - sent
            return sent

    def _run(self) -> None:
        while True:
            try:
                r, _, _ = select.select([self.master, self._stop_r], [], [], 1.0)
            except (OSError, ValueError):
                return
            if self._stop_r in r:
                return
            if self.master in r:
                try:
                    data = os.read(self.master, 65536)
                except BlockingIOError:
                    continue
                except OSError:
                    return
                self.received_bytes += len(data)
                if data and self.on_data is not None:
                    try:
                        self.on_data(data, self.write)
                    except Exception:       # a handler bug must not kill the port silently
                        log.exception("pty handler failed")

    def close(self) -> None:
        if self._closed:
            return
        os.write(self._stop_w, b"x")
        self._thread.join(timeout=5)
        with self._wlock:
            self._closed = True
            for fd in (self.master, self._slave, self._stop_r, self._stop_w):
                try:
                    os.close(fd)
                except OSError:
                    pass

    def __enter__(self) -> PtyEndpoint:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class FlowPtyEndpoint(PtyEndpoint):
    """A pty endpoint whose writes wait for the client to drain the port (flow control) instead
    of dropping at once, as long as the client takes some of the bytes at least every
    ``write_timeout_s``; after one timed-out write it drops
    (counting ``overflow_bytes``) until a write goes through whole again or the client has
    drained the port since (the master is writable again), so a client that went away cannot
    stall the emulator. Needed when the emulator runs many times faster than the nominal baud
    rate would allow. (Before, only a whole write ended the dropping: a stream writing batches
    larger than the port holds -- 2 kHz at 100x, a catch-up batch of the IMU stream thread --
    never had one, and a driver starved once for 0.5 s lost the rest of the stream.)
    The timeout is on the client's progress, not on the whole write: with one deadline for the
    whole write, a catch-up batch larger than the client drains in 0.5 s (333 kB of VectorNav
    frames at 50x, at load 15) was cut although the client read all along (its longest pause
    22 ms), and test_wire_imu_errors / test_hil_faults / test_hil_runs found bytes lost.

    "The client took bytes" is read on the client's side of the pty, not only from the writes:
    the slave's input queue (``FIONREAD`` on the slave this endpoint keeps open) shrank, or is
    empty -- the client has read everything the kernel delivered and waits for more. A loaded
    host can leave the master without room while the client's queue stays empty (the kernel's
    pty buffer work not scheduled, or this writer thread not run, for over 1.5 s at load 17-23
    on 2 cores); counting that as the client's silence dropped bytes its driver was waiting
    for, in select(), with nothing to read (stack samples of tests/test_daemon_wire.py's ten
    link drops): a counter gap in the middle of a read, which paused the run on 'imu-gap' with
    nothing in the record to explain it. Such waits are counted in ``host_waits``; a write still
    gives up after ``host_wait_max_s`` without a byte written, so a jammed port cannot stall
    the emulator for ever.

    Flow control starts once the client has written to the port (``received_bytes``; a
    commanded device's driver always speaks first: GoToConfig, a register read): until then
    nobody may have the port open -- the new pty after a pulled cable, into which the device
    still streams its old measurement period -- and writes drop what does not fit, as
    :class:`PtyEndpoint`'s do (a UART with nobody listening). Waiting there instead made the IMU
    stream thread hand the client, when it opened the port, the frames that became due during
    the wait as one burst of stale data ahead of the reply to its GoToConfig.
    ``flow_before_client_speaks``: a device that takes no commands sets it."""

    #: the client's longest pause (no byte taken) before the port drops, wall s: longer than a
    #: reader thread of a loaded host is held up (0.5 s was not, at load 15-18 on 2 cores: the
    #: wired 24-position runs at 100x lost 4,000-24,000 samples at a time, test_hil_runs)
    write_timeout_s = 1.5
    #: the longest a write waits without writing a byte while its client has taken everything
    #: the port delivered (the host slow, not the client), wall s
    host_wait_max_s = 10.0
    #: writes that waited past ``write_timeout_s`` because the client had taken all the port
    #: delivered: each one dropped bytes before (see the class docstring)
    host_waits = 0
    flow_before_client_speaks = False
    _aborted = False

    def client_queue(self) -> int:
        """Bytes the port has delivered to the client's side and it has not read yet (the slave's
        input queue, ``FIONREAD``); -1 when the port is closed."""
        try:
            return struct.unpack("i", fcntl.ioctl(self._slave, termios.FIONREAD, b"\0\0\0\0"))[0]
        except OSError:
            return -1

    def abort_writes(self) -> None:
        """A write waiting for the client gives up now (the emulator is shutting down)."""
        self._aborted = True

    def close(self) -> None:
        self.abort_writes()
        super().close()

    def write(self, data: bytes) -> int:
        if not getattr(self, "_flowing", True):
            try:
                _, w, _ = select.select([], [self.master], [], 0)
            except (OSError, ValueError):
                w = []
            if w:                       # the client drained the port since: it is there again
                self._flowing = True
        with self._wlock:
            if self._closed:
                return 0
            view, sent = memoryview(data), 0
            flowing = getattr(self, "_flowing", True) and (self.received_bytes > 0 or self.flow_before_client_speaks)
            now = time.monotonic()
            deadline = now + (self.write_timeout_s if flowing else 0.0)
            last_byte, queued, waited_on_host = now, -1, False
            while sent < len(view):
                try:
                    sent += os.write(self.master, view[sent:])
                    if flowing:                 # the client took bytes: it is there, wait on
                        last_byte = time.monotonic()
                        deadline = last_byte + self.write_timeout_s
                except BlockingIOError:
                    now = time.monotonic()
                    if flowing:
                        q = self.client_queue()
                        if q == 0 or 0 <= q < queued:   # the client reads: the host is slow
                            waited_on_host |= now - last_byte >= self.write_timeout_s
                            deadline = max(deadline, min(now + self.write_timeout_s,
                                                         last_byte + self.host_wait_max_s))
                        queued = q
                    left = deadline - now
                    if left <= 0 or self._aborted:
                        break
                    select.select([], [self.master], [], min(left, 0.01))
                except OSError as exc:
                    if exc.errno in (errno.EIO, errno.EBADF):
                        break
                    raise
            self._flowing = sent == len(view)
            self.overflow_bytes += len(view) - sent
            self.host_waits += waited_on_host
            return sent


class FreeRunPtyEndpoint(FlowPtyEndpoint):
    """The port of a device that streams from power-up, whether or not a client listens (the
    declarative-frame IMU): its client never writes, so flow control does not wait for it to
    speak."""

    flow_before_client_speaks = True


class PtyBridge:
    """Null-modem pair: whatever is written to ``path_a`` is read from ``path_b`` and vice versa."""

    def __init__(self, name: str = "bridge") -> None:
        self._a = open_raw_pty()
        self._b = open_raw_pty()
        self.path_a, self.path_b = self._a[2], self._b[2]
        self._stop_r, self._stop_w = os.pipe()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=f"{name}-copier", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        ma, mb = self._a[0], self._b[0]
        peer = {ma: mb, mb: ma}
        while True:
            try:
                r, _, _ = select.select([ma, mb, self._stop_r], [], [], 1.0)
            except (OSError, ValueError):
                return
            if self._stop_r in r:
                return
            for fd in r:
                try:
                    data = os.read(fd, 65536)
                    if data:
                        os.write(peer[fd], data)
                except OSError:
                    continue

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        os.write(self._stop_w, b"x")
        self._thread.join(timeout=5)
        for fd in (self._a[0], self._a[1], self._b[0], self._b[1], self._stop_r, self._stop_w):
            try:
                os.close(fd)
            except OSError:
                pass


class TcpEndpoint:
    """Threaded TCP listener on ``host``; ``address`` is (host, port) after construction."""

    def __init__(self, make_handler: Callable[[], OnData], host: str = "127.0.0.1", port: int = 0,
                 name: str = "tcp") -> None:
        self.make_handler = make_handler
        self._srv = socket.create_server((host, port))
        self._srv.settimeout(0.2)
        self.address: tuple[str, int] = self._srv.getsockname()[:2]
        self._conns: set[socket.socket] = set()
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._threads: list[threading.Thread] = []
        self._name = name
        t = threading.Thread(target=self._accept, name=f"{name}-accept", daemon=True)
        t.start()
        self._threads.append(t)

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                conn, _ = self._srv.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._conns.add(conn)
            t = threading.Thread(target=self._serve, args=(conn,), name=f"{self._name}-conn", daemon=True)
            t.start()
            self._threads.append(t)

    def _serve(self, conn: socket.socket) -> None:
        wlock = threading.Lock()
        on_data = self.make_handler()

        def write(data: bytes) -> None:
            with wlock:
                try:
                    conn.sendall(data)
                except OSError:
                    pass
        try:
            while not self._closed.is_set():
                try:
                    data = conn.recv(65536)
                except OSError:
                    return
                if not data:
                    return
                try:
                    on_data(data, write)
                except Exception:
                    log.exception("tcp handler failed")
        finally:
            with self._lock:
                self._conns.discard(conn)
            conn.close()

    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        self._srv.close()
        with self._lock:
            for c in list(self._conns):
                try:
                    c.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
        for t in self._threads:
            t.join(timeout=5)
