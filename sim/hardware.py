"""Emulated rig hardware on real wires: every server driven by ONE physics world.

``start_hardware(cfg, speed)`` builds the in-process physics of :mod:`rigctl.sim.world` (table
profiles and servo dynamics, IMU error model) on a :class:`~rigctl.clock.ScaledClock` running
``speed`` times real time, and serves it as real hardware would:

* turntable, ACL-style ASCII (:mod:`rigctl.sim.acl_server`) on a pty and on TCP;
* turntable, Modbus register map (:mod:`rigctl.sim.modbus_server`, pymodbus 3.16) on Modbus TCP
  and Modbus RTU over a pty null-modem pair;
* Xsens MTi (:mod:`rigctl.sim.xsens_server`) on a pty, streaming the world's IMU samples;
* climatic chamber (:mod:`rigctl.sim.chamber_servers`): a Watlow F4T on Modbus RTU (pty
  ``chamber-rtu``) and Modbus TCP, and an SCPI chamber on TCP (a PyVISA socket resource);
* NovAtel receiver (:mod:`rigctl.sim.gnss_server`) on a pty, MARK1TIMEA logs of the pulses given
  to :meth:`Hardware.pulse` (or every ``pulse_period_s``).

Time base: one clock for all devices. Table controller time (ACL ``t_ms``, Modbus IR 3-4 and
B+12), Xsens SampleTimeFine (10 kHz ticks since start) and GNSS time (GPS week ``gps_week0`` +
``gps_seconds0`` at clock 0) are all that clock. A hardware loop thread advances the world every
``tick_s`` of wall time; table reads see the state as of the last tick (at most ``tick_s * speed``
of rig time old). An IMU stream thread sends the IMU frames that became due up to the world's
time: its pty writes may wait for a slow client (flow control, :class:`FlowPtyEndpoint`) while
the physics -- the table's controller time -- goes on.

Ports: each pty gets a symlink in ``link_dir`` (a fresh temporary directory unless given):
``table-acl``, ``table-rtu``, ``imu``, ``gnss``. Clients should open the symlink. A simulated
disconnect (:meth:`Hardware.disconnect`) removes the symlink and closes the pty (as a pulled USB
adapter takes its device node), waits, opens a NEW pty and points the SAME symlink to it (the raw
``/dev/pts/N`` path changes; it is returned and logged).

The Xsens MTi answers ReqDID with ``imu_device_id`` (default 0x03780001, printed ``03780001``;
None: the device answers Error, as one without ReqDID would); a test swaps the unit under test by
setting ``hw.xsens.device_id`` and pulling the cable (:meth:`Hardware.disconnect`).

Fault injection (side channel, not the wire): :meth:`set_imu_byte_errors`, :meth:`stall` and
:meth:`release_stall`, :meth:`drop_replies`, :meth:`garble_replies`, :meth:`disconnect`,
:meth:`trip_interlock`, :meth:`trip_following_error`, :meth:`clear_fault` (the operator at the
table), :meth:`inject`, :meth:`pause_physics` (the hardware loop stands still, as when starved of
CPU), :meth:`limit_compute` (``compute_limit=``, ``rigctl sim up --compute-limit``: the physics
runs no faster than a given speed, as on a host too slow for ``speed``).
Observation (side channel, for tests): ``acl.core.received`` (request lines with wall times),
``xsens.measurement_starts`` and, with ``imu_keep_sent=N``, ``xsens.sent`` (the last N batches of
IMU frames put on the wire, with wall times and their float32 values).
"""
from __future__ import annotations

import asyncio
import logging
import math
import os
import shutil
import tempfile
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from rigctl.clock import ScaledClock
from rigctl.config.config import RigConfig
from rigctl.drivers.modbus_map import SCALE_POSITION, FaultCode
from rigctl.drivers.xsens import FREQ_MAX, MID, SAMPLE_TIME_FINE_HZ, encode_mtdata2, mtdata2_frame_bytes

from .acl_server import AclServer, AclServerCore, _LineHandler
from .gnss_server import GnssServer
from .links import FlowPtyEndpoint, FreeRunPtyEndpoint, PtyEndpoint
from .modbus_server import ModbusTableServer
from .physics_table import ImuTap, PhysicsTable
from .world import SimWorld
from .xsens_server import MAX_BATCH, XsensServer

log = logging.getLogger(__name__)
#: IMU protocols the emulator serves on the pty 'imu' (one at a time)
IMU_PROTOCOLS = ("xsens", "vectornav", "frame")


class _Stall:
    """The next ``replies`` replies of a controller come ``seconds`` late, or (``seconds`` inf)
    only once :meth:`release` is called; ``held`` counts the replies being held back now."""

    def __init__(self) -> None:
        self.replies, self.seconds, self.held = 0, 0.0, 0
        self._released = threading.Event()

    def arm(self, seconds: float, replies: int) -> None:
        self._released.clear()
        self.seconds, self.replies = float(seconds), int(replies)

    def release(self) -> None:
        self._released.set()

    def take(self) -> bool:
        """Whether this reply is held back (then counted in ``held`` until :meth:`done`)."""
        if self.replies <= 0:
            return False
        self.replies -= 1
        self.held += 1
        return True

    def wait(self) -> None:
        self._released.wait(None if math.isinf(self.seconds) else self.seconds)

    def is_released(self) -> bool:
        return self._released.is_set()

    def done(self) -> None:
        self.held -= 1


class HwAclCore(AclServerCore):
    """ACL protocol core with a counted stall (:class:`_Stall`, :meth:`Hardware.stall`: the
    port's reader thread waits, as a busy controller would). Every request line is kept in
    :attr:`received` as (wall time ``time.monotonic()``, line), the last 20,000, so a test can
    see which commands reached the controller and when."""

    def __init__(self, *args: Any, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.received: deque[tuple[float, str]] = deque(maxlen=20_000)
        self.stalls = _Stall()

    def handle_line(self, line: str | bytes) -> str | None:
        self.received.append((time.monotonic(), line.decode("ascii", "replace").strip()
                              if isinstance(line, bytes) else line.strip()))
        if self.stalls.take():
            try:
                self.stalls.wait()
            finally:
                self.stalls.done()
        return super().handle_line(line)


class HwModbusServer(ModbusTableServer):
    """Modbus table server with a counted stall (:class:`_Stall`, :meth:`Hardware.stall`)."""

    def __init__(self, *args: Any, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.stalls = _Stall()

    async def _action(self, fc, start, address, count, registers, set_values):
        if self.stalls.take():
            try:
                end = time.monotonic() + self.stalls.seconds
                while not self.stalls.is_released() and time.monotonic() < end:
                    await asyncio.sleep(0.01)
            finally:
                self.stalls.done()
        return await super()._action(fc, start, address, count, registers, set_values)


class HwXsensServer(XsensServer):
    """Xsens emulator stepped by the hardware's IMU stream thread (no thread of its own); a
    measurement period starts on the world's sample grid so its frames carry exact world
    samples."""

    grid_rate_hz = 100.0

    def __init__(self, *args: Any, keep_sent: int = 0, **kw: Any) -> None:
        #: wall times (``time.monotonic()``) at which a measurement period began (GoToMeasurement)
        self.measurement_starts: list[float] = []
        #: with ``keep_sent`` > 0, the last ``keep_sent`` batches written to the port as [wall
        #: time after the write, sample times (n,) s, acceleration (n, 3) as the float32 values
        #: on the wire, whether the port took every byte]: what a client could have received. A
        #: batch is listed from the moment its write begins (with that time, and False) until
        #: the write ends: a flow-controlled write of a large batch (the IMU stream thread
        #: catching up) can take a while, and the client has its first frames before it ends
        self.sent: deque[tuple[float, np.ndarray, np.ndarray, bool]] = deque(maxlen=max(1, keep_sent))
        self.keep_sent = int(keep_sent)
        self._last_acc: np.ndarray | None = None
        #: held by step() from encoding a batch until its write ends, and by GoToConfig / Reset
        #: before they stop the stream: frames encoded before the request reach the wire before
        #: its acknowledgement, as a device's do (before, a batch encoded just before GoToConfig
        #: could be written after the ack, and a reconnecting driver took those frames of the old
        #: measurement period for its own: stamped before its session began)
        self._wire = threading.Lock()
        #: cleared while a GoToConfig / Reset waits for (or holds) the wire: step() lets it go
        #: first. A Lock is not fair, and the stream thread, catching up batch after batch, took
        #: the wire again before the waiting request thread woke up
        self._wire_free = threading.Event()
        self._wire_free.set()
        super().__init__(*args, **kw)

    def _stream(self) -> None:          # Hardware._imu_loop calls step() instead
        return

    def _handle(self, mid: int, data: bytes) -> bytes:
        if mid in (MID.GO_TO_CONFIG, MID.RESET):
            self._wire_free.clear()
            try:
                with self._wire:
                    return super()._handle(mid, data)
            finally:
                self._wire_free.set()
        return super()._handle(mid, data)

    #: the uncapped clock (set by :class:`Hardware`): a measurement period starts NOW even when
    #: the physics lags behind (e.g. the loop was starved of CPU), so no frame
    #: of it carries a device time from before the GoToMeasurement request
    true_clock: Any = None

    def _enter_measurement(self) -> None:
        g = self.grid_rate_hz
        now = self.true_clock() if self.true_clock is not None else self.clock()
        self._t0, self._k = math.ceil(now * g - 1e-9) / g, 0
        self.state = "measurement"
        self.measurement_starts.append(time.monotonic())

    #: byte errors injected so far, and hit frames whose 8-bit checksum still adds up after the
    #: corruption (no receiver can detect those; with 2+ errors in one frame about 1 in 256)
    errors_injected = 0
    frames_hit_undetectable = 0
    _err_pending: np.ndarray | None = None
    _err_values: np.ndarray | None = None
    _stream_bytes = 0
    _stream_frames = 0

    def _encode(self, k: np.ndarray) -> bytes:
        """As the base class, but byte errors are a renewal process over the byte stream
        (geometric gaps with mean 1/rate, XOR values 1..255, drawn in fixed-size chunks), so the
        error positions depend only on the seed, not on how the stream is cut into batches."""
        rate, self.byte_error_rate = self.byte_error_rate, 0.0
        try:
            data = self._encode_single_layout(k) if all(
                it.freq_hz in (0, FREQ_MAX, self.rate_hz) for it in self.config) else super()._encode(k)
        finally:
            self.byte_error_rate = rate
        size, n = len(data), len(k)
        start, self._stream_bytes = self._stream_bytes, self._stream_bytes + size
        self._stream_frames += n
        if rate <= 0:
            self._err_pending = None
            return data
        pos, vals = self._error_positions(start, start + size, rate)
        if not pos.size:
            return data
        out = np.frombuffer(data, np.uint8).copy()
        out[pos - start] ^= vals
        lengths = out[3::out[3] + 5] if size == n * (int(out[3]) + 5) else None
        if lengths is not None and (lengths == out[3]).all():
            bounds = np.arange(1, n + 1) * (int(out[3]) + 5)
        else:                                       # mixed layouts: walk the (clean) frames
            clean = np.frombuffer(data, np.uint8)
            ends, i = [], 0
            while i < size:
                i += int(clean[i + 3]) + 5
                ends.append(i)
            bounds = np.asarray(ends)
        hit = np.unique(np.searchsorted(bounds, pos - start, side="right"))
        self.frames_hit += int(hit.size)
        self.errors_injected += int(pos.size)
        lo = np.concatenate(([0], bounds[:-1]))
        clean = np.frombuffer(data, np.uint8)
        for fi in hit.tolist():
            a, b = int(lo[fi]), int(bounds[fi])
            if (out[a] == 0xFA and out[a + 1] == 0xFF and out[a + 3] == clean[a + 3]
                    and int(out[a + 1:b].sum()) % 256 == 0):
                self.frames_hit_undetectable += 1
        return out.tobytes()

    def _encode_single_layout(self, k: np.ndarray) -> bytes:
        """Fast path of the base class's encoder when every item is in every packet."""
        t = self._t0 + k / self.rate_hz
        n = len(k)
        f = dict(self.source(t))
        f["packet_counter"] = self.counter + np.arange(n)
        f["sample_time_fine"] = self.stf_offset + np.round((t - self.t_origin) * SAMPLE_TIME_FINE_HZ).astype(np.int64)
        f.setdefault("status_word", np.zeros(n, dtype=np.int64))
        if self.keep_sent:
            self._last_acc = np.asarray(f["acceleration"], dtype=np.float32)
        self.counter += n
        self.frames_sent += n
        return encode_mtdata2([it.xdi for it in self.config], f).tobytes()

    def _error_positions(self, start: int, end: int, rate: float) -> tuple[np.ndarray, np.ndarray]:
        if self._err_pending is None:
            self._err_pending, self._err_values = np.empty(0, np.int64), np.empty(0, np.uint8)
            self._err_next = start
        while not self._err_pending.size or self._err_pending[-1] < end:
            gaps = self._rng.geometric(rate, 4096)
            pos = self._err_next - 1 + np.cumsum(gaps)
            self._err_next = int(pos[-1]) + 1
            self._err_pending = np.concatenate((self._err_pending, pos))
            self._err_values = np.concatenate((self._err_values, self._rng.integers(1, 256, 4096).astype(np.uint8)))
        m = int(np.searchsorted(self._err_pending, end))
        keep = self._err_pending[:m] >= start
        pos, vals = self._err_pending[:m][keep], self._err_values[:m][keep]
        self._err_pending, self._err_values = self._err_pending[m:], self._err_values[m:]
        return pos, vals

    def next_time(self) -> float | None:
        """Time of the next frame not yet encoded, s (None when not measuring): the physics
        loop keeps the tap's samples from there on (:meth:`Hardware._trim_tap`)."""
        return self._t0 + self._k / self.rate_hz if self.state == "measurement" else None

    #: bytes of frames encoded and written per step at most (268 frames of 61 bytes): a
    #: GoToConfig / Reset waits for the batch on the wire, so its acknowledgement comes after at
    #: most one such write, as a device's comes after the frames already in its UART. Steps of up
    #: to MAX_BATCH frames (20,000 frames, 1.2 MB: the stream catching up at 100x on a loaded
    #: host), each written whole at the pace of the client's reads, held the request for 1-5 s,
    #: past the driver's 3 tries of 0.5 s: 'no acknowledgement of GoToConfig' / 'no stream' at
    #: connect
    wire_bytes = 16384

    def step(self, until: float) -> int:
        """Encode and send the frames due up to time ``until``, at most :attr:`wire_bytes`;
        returns the count (0: none due, or not measuring)."""
        self._wire_free.wait()
        with self._wire:
            return self._step(until)

    def _step(self, until: float) -> int:
        with self._lock:
            if self.state != "measurement":
                return 0
            most = max(1, self.wire_bytes // mtdata2_frame_bytes([it.xdi for it in self.config]))
            n = min(max(int(math.floor((until - self._t0) * self.rate_hz + 1e-9)) + 1 - self._k, 0), most)
            if n == 0:
                return 0
            k = self._k + np.arange(n)
            self._last_acc = None
            frames = self._encode(k)
            # counted as sent only once encoded: the physics loop reads next_time() without
            # this lock and trims the tap's samples before it, so a count raised before the
            # encoder read its samples let the trim take them away (the tap then gave every
            # frame of the batch the first sample it still had: 30-180 frames of one frozen
            # sample, several times per 24-position run; tests/test_hil_tap.py)
            self._k += n
            acc = self._last_acc
            record = [time.monotonic(), self._t0 + k / self.rate_hz, acc, False] \
                if self.keep_sent and acc is not None else None
        if record is not None:      # kept from the start: the client may have part of it before the
            self.sent.append(record)  # write ends (a flow-controlled write waits for it to read)
        sent = self.port.write(frames)
        if record is not None:
            record[0], record[3] = time.monotonic(), sent == len(frames)
        return n


class _Slot:
    """A pty endpoint of a server, published through a symlink that survives reconnects."""

    def __init__(self, name: str, link: Path, make, attach) -> None:
        self.name, self.link, self.make, self.attach = name, link, make, attach
        self.endpoint: PtyEndpoint = make()
        attach(self.endpoint)
        self.reconnects = 0
        self._point()

    def _point(self) -> None:
        tmp = self.link.with_name(self.link.name + ".new")
        if tmp.is_symlink():
            tmp.unlink()
        os.symlink(self.endpoint.path, tmp)
        os.replace(tmp, self.link)

    def disconnect(self, down_s: float) -> str:
        self.unplug()
        time.sleep(down_s)
        return self.replug()

    def unplug(self) -> None:
        """Pull the cable: the symlink and the pty go (:meth:`replug` puts a new one in)."""
        self._old = self.endpoint
        # a pulled cable takes its device node with it (a USB serial adapter's /dev/ttyUSB0): the
        # symlink goes too, or a reconnect during the outage could open the old pty's number
        # already handed to another process's new pty (seen with two test runs at once)
        if self.link.is_symlink():
            self.link.unlink()
        self._old.close()

    def replug(self) -> str:
        """Plug a new pty in at the same symlink; returns its path."""
        old = self._old
        self.endpoint = self.make()
        self.attach(self.endpoint)
        self._point()
        self.reconnects += 1
        log.info("%s: pty reconnected: %s -> %s (symlink %s)", self.name, old.path, self.endpoint.path, self.link)
        return self.endpoint.path

    def close(self) -> None:
        self.endpoint.close()
        if self.link.is_symlink():
            self.link.unlink()


class _CappedClock:
    """The world's view of the shared clock: never more than ``cap`` (set by the hardware loop),
    so an emulator asked to run faster than it can compute falls behind gracefully (bounded work
    per tick, reported as :attr:`Hardware.lag_s`) instead of melting down."""

    def __init__(self, clock: ScaledClock) -> None:
        self.clock, self.cap = clock, math.inf

    def now(self) -> float:
        return min(self.clock.now(), self.cap)

    def sleep(self, seconds: float) -> None:
        self.clock.sleep(seconds)


class Hardware:
    """The running emulated hardware; see the module docstring. Use :func:`start_hardware`."""

    def __init__(self, cfg: RigConfig, speed: float = 1.0, *, link_dir: str | Path | None = None,
                 imu_baudrate: int = 921_600, imu_max_rate_hz: int = 2000, rtu_baudrate: int = 115_200,
                 acl_tcp_port: int = 0, modbus_tcp_port: int = 0, modbus_word_order: str = "big",
                 modbus_unit_id: int = 1, tick_s: float = 0.002, pulse_period_s: float | None = None,
                 seed: int = 0, imu_keep_sent: int = 0, imu_device_id: int | None = 0x03780001,
                 imu_protocol: str = "xsens", imu_frame: dict | None = None,
                 compute_limit: float | None = None) -> None:
        if compute_limit is not None and not compute_limit > 0:
            raise ValueError(f"compute_limit must be positive, not {compute_limit!r}")
        #: the physics advances at most this many times real time (None: as fast as the host
        #: computes): a host too slow for ``speed``, on any machine (tests, docs/emulator.md)
        self.compute_limit = compute_limit
        self._limit: tuple[float, float, float] | None = None   # (wall, rig time, x real time)
        if imu_protocol not in IMU_PROTOCOLS:
            raise ValueError(f"imu_protocol must be one of {IMU_PROTOCOLS}, not {imu_protocol!r}")
        self.imu_protocol = imu_protocol
        self.imu_frame = imu_frame
        self.cfg, self.speed, self.tick_s = cfg, float(speed), float(tick_s)
        self.imu_device_id = imu_device_id
        self.imu_baudrate, self.rtu_baudrate = imu_baudrate, rtu_baudrate
        self.modbus_word_order, self.modbus_unit_id = modbus_word_order, modbus_unit_id
        self._own_dir = link_dir is None
        self.link_dir = Path(tempfile.mkdtemp(prefix="rigctl-sim-") if link_dir is None else link_dir)
        self.link_dir.mkdir(parents=True, exist_ok=True)
        self._closers: list = []
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.pulse_period_s = pulse_period_s
        self._next_pulse = 0.0
        self._paused_until = 0.0
        self.imu_keep_sent = int(imu_keep_sent)
        try:
            self._build(acl_tcp_port, modbus_tcp_port, imu_max_rate_hz, seed)
        except BaseException:
            self.close()
            raise

    def _build(self, acl_tcp_port: int, modbus_tcp_port: int, imu_max_rate_hz: int, seed: int) -> None:
        self.clock = ScaledClock(self.speed)
        self.world_clock = _CappedClock(self.clock)
        self.lock = threading.RLock()
        self.world = SimWorld(self.cfg, self.world_clock)
        self.table = PhysicsTable(self.world, self.lock, self.cfg.limits)
        self.tap = ImuTap(self.world, self.lock)
        # the world's first step, before any port or thread exists and before the clock starts:
        # it loads the noise kernels (numba: ~0.1 s from its cache through rigctl.jit, 3.4 s
        # compiling on a clean clone, seconds more on a loaded host). Taken by the physics
        # loop's first tick instead, under the hardware lock, it held back the first table
        # commands of a client that connected as soon as the ports were up (`rigctl sim up` at
        # 100x under load: 0.2-1.3 s for the reply to the first command after 'ready', past the
        # wired config's 0.5 s timeout)
        self.world_clock.cap = 0.0
        self.world.advance()
        self.world_clock.cap = math.inf
        self.clock = self.world_clock.clock = ScaledClock(self.speed)
        if self.compute_limit is not None:
            self.limit_compute(self.compute_limit)
        # turntable, ASCII
        self.acl = AclServer(self.table)
        self.acl.core = HwAclCore(self.table)
        self._closers.append(self.acl.close)
        self.slots: dict[str, _Slot] = {}
        self._slot("table-acl", lambda: PtyEndpoint(_LineHandler(self.acl.core), name="acl-pty"), lambda ep: None)
        self.acl_tcp = self.acl.open_tcp(port=acl_tcp_port)
        # turntable, Modbus
        servo = self.world.table.axes[0].servo
        self.modbus = HwModbusServer(self.table, device_id=self.modbus_unit_id, word_order=self.modbus_word_order,
                                     window_udeg=int(round(servo.in_position_window / SCALE_POSITION)),
                                     dwell_ms=int(round(servo.dwell_s * 1e3)))
        self._closers.append(self.modbus.close)
        self.modbus_tcp = self.modbus.start_tcp(port=modbus_tcp_port)
        rtu = self.modbus.start_rtu(baudrate=self.rtu_baudrate)
        self._link("table-rtu", rtu)
        # IMU: one protocol on the pty 'imu' (Xsens MT, VectorNav binary or a declarative frame)
        self.xsens: HwXsensServer | None = None
        if self.imu_protocol == "xsens":
            HwXsensServer.grid_rate_hz = self.world.rate_hz
            self.xsens = HwXsensServer(source=self.tap, clock=self.world_clock.now, baudrate=self.imu_baudrate,
                                       max_rate_hz=max(imu_max_rate_hz, int(self.world.rate_hz)), seed=seed,
                                       keep_sent=self.imu_keep_sent, device_id=self.imu_device_id)
            self.imu_server = self.xsens
        elif self.imu_protocol == "vectornav":
            from .vectornav_server import VectorNavServer
            VectorNavServer.grid_rate_hz = self.world.rate_hz
            self.imu_server = VectorNavServer(self.tap, self.world_clock.now, baudrate=self.imu_baudrate, seed=seed)
        else:
            from rigctl.config.frame_spec import parse_frame_spec
            from rigctl.yamlio import LocDict

            from .frame_server import EXAMPLE, FrameServer
            FrameServer.grid_rate_hz = self.world.rate_hz
            self.imu_frame = self.imu_frame or EXAMPLE
            spec = parse_frame_spec(LocDict({"frame": self.imu_frame}))
            self.imu_server = FrameServer(spec, self.tap, self.world_clock.now, rate_hz=self.world.rate_hz,
                                          seed=seed)
        self.imu_server.true_clock = self.clock.now
        self._closers.append(self.imu_server.close)
        self._replace_port(self.imu_server, "imu", FreeRunPtyEndpoint if self.imu_protocol == "frame"
                           else FlowPtyEndpoint)
        # climatic chamber: Watlow F4T on Modbus RTU (pty) and TCP, SCPI on TCP (sim/chamber_servers.py)
        from .chamber_servers import ChamberAccess, ScpiChamberServer, WatlowF4TServer
        self.chamber = ChamberAccess(self.world.chamber, lambda: self.world.t, self.lock)
        self.watlow = WatlowF4TServer(self.chamber)
        self._closers.append(self.watlow.close)
        self.watlow_tcp = self.watlow.start_tcp()
        self._link("chamber-rtu", self.watlow.start_rtu(baudrate=self.rtu_baudrate))
        self.scpi = ScpiChamberServer(self.chamber)
        self._closers.append(self.scpi.close)
        # GNSS receiver
        self.gnss = GnssServer(clock=self.world_clock.now, source=self._periodic_pulses)
        self._closers.append(self.gnss.close)
        self._replace_port(self.gnss, "gnss", PtyEndpoint)
        self._imu_t = 0.0                   # world time the IMU stream may reach (set by the loop)
        self._imu_due = threading.Condition()
        for target, name in ((self._loop, "hardware-loop"), (self._imu_loop, "imu-stream")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)

    # ------------------------------------------------------------------------- plumbing
    def _link(self, name: str, target: str) -> None:
        link = self.link_dir / name
        if link.is_symlink():
            link.unlink()
        os.symlink(target, link)
        self._closers.append(lambda: link.unlink() if link.is_symlink() else None)

    def _slot(self, name: str, make, attach) -> _Slot:
        slot = _Slot(name, self.link_dir / name, make, attach)
        self.slots[name] = slot
        self._closers.append(slot.close)
        return slot

    def _replace_port(self, server: Any, name: str, cls: type[PtyEndpoint]) -> None:
        """Move a server's pty into a slot (reconnectable, symlinked)."""
        server.port.close()

        def attach(ep: PtyEndpoint) -> None:
            server.port, server.path = ep, ep.path
        self._slot(name, lambda: cls(server._on_data, name=f"{name}-pty"), attach)

    def _periodic_pulses(self) -> list[float]:
        if not self.pulse_period_s:
            return []
        now, out = self.world_clock.now(), []
        while self._next_pulse <= now:
            out.append(self._next_pulse)
            self._next_pulse += self.pulse_period_s
        return out

    def _loop(self) -> None:
        """Physics: advance the world every tick and buffer its IMU samples in the tap for the
        IMU stream thread (:meth:`_imu_loop`). The stream's pty writes wait for a slow client
        (flow control) in that thread, not here: when they ran in this loop, a client slow to drain
        the port at connect stood the physics still for up to 0.5 s of wall time (50 s of rig
        time at 100x) -- the table's controller time with it -- and the drivers learnt time
        offsets that late. Only a backlog beyond ``backlog`` samples (the client slower than the
        stream for seconds: the emulator runs faster than the wire) holds the physics back."""
        horizon = int(2.0 * self.world.rate_hz) + MAX_BATCH
        # >= the port's flow-control wait + 0.5 s of wall time: a client paused for less than the
        # wait gets every frame and the physics does not stop meanwhile
        backlog = max(horizon, int(self.world.rate_hz * self.speed * (FlowPtyEndpoint.write_timeout_s + 0.5)))
        chunk_s = MAX_BATCH / self.world.rate_hz
        while not self._stop.wait(self.tick_s):
            if time.monotonic() < self._paused_until:
                continue
            try:
                nt = self.imu_server.next_time()
                if nt is not None and self.world.k - int(round(nt * self.world.rate_hz)) > backlog:
                    continue                                    # the stream is far behind: wait
                with self.lock:
                    if time.monotonic() < self._paused_until:   # paused since the check above
                        continue
                    cap = self.table._t() + chunk_s
                    if self._limit is not None:             # a host slower than speed asks
                        w0, t0, x = self._limit
                        cap = min(cap, t0 + (time.monotonic() - w0) * x)
                    self.world_clock.cap = cap
                    self.world.advance()
                    self.tap.pull()
                    t = self.table._t()
                with self._imu_due:
                    self._imu_t = t
                    self._imu_due.notify()
                self._trim_tap(horizon)
            except Exception:       # the loop must survive a bug in one device
                log.exception("hardware loop")

    def _trim_tap(self, horizon: int) -> None:
        """Forget the tap's samples that no frame will need: those before the IMU server's
        next frame not yet encoded (its ``next_time``), or more than ``horizon`` samples behind
        the world while it does not stream. Runs in the physics loop, concurrently with the
        stream thread's encoding (which therefore counts a batch only once encoded)."""
        nt = self.imu_server.next_time()
        keep = int(round(nt * self.world.rate_hz)) if nt is not None else self.world.k - horizon
        self.tap.trim(min(keep, self.world.k - 1))

    def _imu_loop(self) -> None:
        """IMU stream: encode and send the frames due up to the world time the physics loop
        reached (its writes may wait for the client; see :meth:`_loop`)."""
        done = -math.inf
        while not self._stop.is_set():
            with self._imu_due:
                if self._imu_t <= done:
                    self._imu_due.wait(0.05)
                t = self._imu_t
            try:
                while self.imu_server.step(t) and not self._stop.is_set():
                    pass                            # more than one batch was due
                done = t
            except Exception:
                log.exception("IMU stream")
                self._stop.wait(0.1)

    # ------------------------------------------------------------------------ endpoints
    @property
    def endpoints(self) -> dict[str, str]:
        """Where clients connect: pty symlinks, ``socket://`` URLs and Modbus host:port."""
        return {"table_acl_pty": str(self.slots["table-acl"].link),
                "table_acl_tcp": f"socket://{self.acl_tcp[0]}:{self.acl_tcp[1]}",
                "table_modbus_tcp": f"{self.modbus_tcp[0]}:{self.modbus_tcp[1]}",
                "table_modbus_rtu": str(self.link_dir / "table-rtu"),
                f"imu_{self.imu_protocol}_pty": str(self.slots["imu"].link),
                "gnss_novatel_pty": str(self.slots["gnss"].link),
                "chamber_watlow_rtu": str(self.link_dir / "chamber-rtu"),
                "chamber_watlow_tcp": f"{self.watlow_tcp[0]}:{self.watlow_tcp[1]}",
                "chamber_scpi_visa": f"TCPIP::{self.scpi.address[0]}::{self.scpi.address[1]}::SOCKET"}

    @property
    def lag_s(self) -> float:
        """How far the physics is behind the clock, s of rig time (grows when ``speed`` x IMU
        rate exceeds what the emulator can compute; about tick_s x speed when it keeps up)."""
        return self.clock.now() - self.table.time()

    def truth(self) -> dict[str, Any]:
        """The emulator's true parameters (JSON-able), as in an in-process run."""
        return self.world.truth()

    # --------------------------------------------------------------------- fault injection
    def set_imu_byte_errors(self, rate: float, seed: int | None = None) -> None:
        """XOR random non-zero values into the IMU stream's bytes, each byte hit with probability
        ``rate`` (from the next frame on); ``self.xsens.frames_hit`` counts the MTData2 frames
        that received at least one error, ``frames_hit_undetectable`` those among them whose
        checksum still adds up."""
        imu = self.imu_server
        with imu._lock:
            imu.byte_error_rate = float(rate)
            imu._err_pending = None
            if seed is not None:
                imu._rng = np.random.default_rng(seed)

    def stall(self, device: str, seconds: float = math.inf, replies: int = 1) -> None:
        """The next ``replies`` replies of ``device`` (``acl`` | ``modbus``) come ``seconds`` late
        (wall), or by default only once :meth:`release_stall` is called: a test of a driver's
        reply timeout then does not depend on how fast this host runs the two sides.
        ``self.acl.core.stalls.held`` / ``self.modbus.stalls.held``: replies held back now."""
        self._stalls(device).arm(seconds, replies)

    def release_stall(self, device: str) -> None:
        """The replies ``device`` holds back (:meth:`stall`) go out now."""
        self._stalls(device).release()

    def _stalls(self, device: str) -> _Stall:
        return {"acl": self.acl.core, "modbus": self.modbus}[device].stalls

    def limit_compute(self, speed: float | None) -> None:
        """From now on the physics advances at most ``speed`` times real time (None: no limit),
        as on a host that computes the rig no faster: its devices' time (table controller time,
        IMU sample times) then falls behind the clock when ``speed`` < :attr:`speed`."""
        self.compute_limit = speed
        self._limit = None if speed is None else (time.monotonic(), self.table._t(), float(speed))

    def pause_physics(self, wall_s: float) -> None:
        """The hardware loop stops for ``wall_s`` of wall time (``wall_s * speed`` of rig time), as
        when it is starved of CPU: the world, the table's controller time and the IMU stream
        stand still while the ports keep answering (table reads see the state of the last tick);
        then it catches up.

        The world's clock is capped at the world's time meanwhile: a command to a device brings
        the world to the clock first (PhysicsTable._now), and with the cap of the loop's last
        tick (up to a chunk of MAX_BATCH samples ahead, 200 s of rig time at 100 Hz) the stop
        command of a 'paused' table advanced the world by the wall time since the pause, x
        ``speed``, and the table then read as stopped: a host stall of 2.5 ms at 100x was enough
        (tests/test_safe_state_slow_table.py at load ~12). ``wall_s`` 0 ends a pause now."""
        self._paused_until = time.monotonic() + float(wall_s)
        if wall_s > 0:
            with self.lock:
                self.world_clock.cap = self.table._t()

    def drop_replies(self, n: int = 1) -> None:
        """The ACL table swallows its next ``n`` replies (Modbus: use :meth:`stall` beyond the
        client's timeout -- pymodbus offers no way to drop a reply from the server side)."""
        self.acl.core.drop_replies += int(n)

    def garble_replies(self, n: int = 1) -> None:
        """The ACL table corrupts its next ``n`` replies."""
        self.acl.core.garble_replies += int(n)

    def disconnect(self, name: str, down_s: float = 0.2, block: bool = True) -> str | None:
        """Pull the cable of pty ``name`` (``table-acl`` | ``imu`` | ``gnss``) for ``down_s`` wall
        seconds, then plug a new pty in at the same symlink. Returns the new pty path (None if
        ``block`` is False: the cable is pulled at once, the outage and the new pty follow in a
        background thread)."""
        slot = self.slots[name]
        if block:
            return slot.disconnect(down_s)
        slot.unplug()

        def replug() -> None:
            if not self._stop.wait(down_s):
                slot.replug()
        t = threading.Thread(target=replug, name=f"disconnect-{name}", daemon=True)
        t.start()
        self._threads.append(t)
        return None

    def power_cycle(self, down_s: float = 0.2, block: bool = True) -> str | None:
        """The IMU loses power for ``down_s`` wall seconds (not just its cable): its pty goes as
        in :meth:`disconnect`, and when power is back the unit restarts -- its device time
        (Xsens SampleTimeFine and PacketCounter, VectorNav TimeStartup) begins again from 0, it
        has a new turn-on bias (:meth:`rigctl.sim.world.SimWorld.power_cycle_imu`: drawn from the
        model's bias repeatability) and it waits to be configured -- before the new pty is plugged in. A driver sees a link loss
        whose device time does not continue (``time_restarts`` / ``device_restarts``); after
        :meth:`disconnect` it continues. Returns the new pty path (None if not ``block``)."""
        restart = getattr(self.imu_server, "power_cycle", None)
        if restart is None:
            raise ValueError(f"a power cycle is not emulated for the {self.imu_protocol!r} IMU protocol; "
                             "use disconnect('imu') for a cable pull")
        slot = self.slots["imu"]
        slot.unplug()

        def back() -> str:
            restart()
            with self.lock:             # the physics computes on with the new turn-on bias
                self.world.power_cycle_imu()
            return slot.replug()
        if block:
            time.sleep(down_s)
            return back()

        def later() -> None:
            if not self._stop.wait(down_s):
                back()
        t = threading.Thread(target=later, name="power-cycle-imu", daemon=True)
        t.start()
        self._threads.append(t)
        return None

    def clear_fault(self, close_interlocks: bool = True) -> None:
        """The operator at the table: reset every tripped axis (fault bits cleared, interlock
        open) and, by default, close the interlocks again so the controller accepts motion."""
        self.table.interlock_reset()
        if close_interlocks:
            for axis in (1, 2, 3):
                self.table.interlock_close(axis)

    def trip_interlock(self, axis: int) -> None:
        self.table.trip(axis, FaultCode.INTERLOCK_TRIP)

    def trip_following_error(self, axis: int) -> None:
        self.table.trip(axis, FaultCode.FOLLOWING_ERROR)

    def inject(self, name: str, data: bytes) -> None:
        """Write raw bytes to the client side of pty ``name`` (e.g. a mark log with a bad CRC)."""
        self.slots[name].endpoint.write(data)

    def pulse(self, t: float | None = None) -> bool:
        """A mark pulse at rig time ``t`` (default now) on the GNSS receiver's MARK1 input and,
        with a VectorNav IMU, on its SYNC_IN (the same tap wired to both)."""
        t = self.world_clock.now() if t is None else float(t)
        if hasattr(self.imu_server, "syncin"):
            self.imu_server.syncin(t)
        return self.gnss.pulse(t)

    # -------------------------------------------------------------------------- teardown
    def close(self) -> None:
        self._stop.set()
        for slot in self.slots.values() if hasattr(self, "slots") else ():
            if isinstance(slot.endpoint, FlowPtyEndpoint):
                slot.endpoint.abort_writes()     # the IMU stream thread may wait for its client
        for t in self._threads:
            t.join(timeout=5)
        self._threads.clear()
        while self._closers:
            try:
                self._closers.pop()()
            except Exception:  # noqa: BLE001 - keep tearing down
                log.exception("closing emulated hardware")
        if self._own_dir:
            shutil.rmtree(self.link_dir, ignore_errors=True)

    def __enter__(self) -> Hardware:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def start_hardware(cfg: RigConfig, speed: float = 1.0, **kw: Any) -> Hardware:
    """Start the emulated hardware for the physics of ``cfg`` at ``speed`` x real time."""
    return Hardware(cfg, speed, **kw)
