"""The streaming IMU drivers' common base (:class:`StreamReader`: reader thread, batched reads,
offset learning, aligned ``read``; Xsens derives from it too) and :class:`StreamImu`, the base of
those that are not Xsens (VectorNav binary, declarative frames): batched vectorised decoding, the
device time base mapped onto the run clock, link loss and reconnect.

A subclass provides ``_new_stream()`` (a decoder with ``feed``/``flush`` and ``counters``),
``_device_time(out) -> (n,) float s`` (unwrapped device time of each decoded frame, NaN when
unknown), ``_inertial(out) -> (acc (n,3) m/s^2, gyro (n,3) rad/s, temperature (n,) degC)`` and
``_configure_device()`` (commands, identity; called with the link open, on every (re)connect).

After a reconnect, a device whose time went back (it restarted: a USB sensor power-cycles with
its cable) -- or jumped ahead of the clock (a restart that a wrapping time field reads as a wrap:
its first sample would be stamped after its arrival) -- is rebased (``device_restarts``): its new timeline is shifted onto the old one, the
shift learnt like the offset (the minimum over the chunks arriving within ``learn_s``, in rig
time, of arrival - offset - newest device time; the new samples are held until then), so the
outage is a counted gap, not a stream of rejected frames, and the time base goes on as before.
``read`` never hands out a sample stamped after ``clock.now()`` (one that came faster than any
chunk of the learning window waits for the next read).

Time base (units s): ``ImuBlock.counter = round((t_dev - t_dev_first) * rate_hz)`` (a gap means
samples that never arrived: ``dropped_samples``); a frame whose device time does not advance is
rejected (``out_of_order``); ``ImuBlock.time = t_dev + offset`` with the offset learnt while the
stream starts as the minimum over arriving chunks of (rig clock at arrival - t_dev of the newest
sample), and kept tracking that minimum (the lower envelope of the latencies) for the rest of the
run when it falls by more than 20 ms of wall time (in rig time): a late chunk can only raise the
estimate, so a stall that spans the learning window at connect is corrected by the first timely
chunk (``offset_corrections``; samples that the lower offset would stamp at or before one already
handed out are dropped, ``restamp_dropped``).
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import asdict

import numpy as np

from rigctl.devices import Clock, DeviceFault, ImuBlock, LinkLost
from rigctl.errors import InputError

from .reader_thread import ReconnectingReader
from .serial_link import SerialLink

log = logging.getLogger(__name__)
#: Bytes are decoded in batches: after the first byte, the reader keeps reading for 20 ms of rig
#: time (``batch_wait_s``; 20 ms of wall time at 1x, 0.2 ms at 100x) -- or, when a read of at least
#: BURST_BYTES shows a burst (a pty carries about 4 KiB per read), for BURST_WAIT_S of wall time --
#: up to BURST_MAX bytes, since a vectorised decoder costs ~0.4 ms per call plus ~1 us per frame.
BURST_BYTES, BURST_WAIT_S, BURST_MAX = 4000, 0.002, 1 << 18


class StreamImuConfigError(InputError, RuntimeError):
    """The device refused (or never acknowledged) the configuration of the rig config (rate,
    baud rate, output): fix the config (:class:`rigctl.errors.InputError`, exit code 2)."""


class StreamImuUnitChanged(DeviceFault):
    """After a reconnect another unit (another serial number) is on the port (a device fault,
    exit code 1; fatal for the reader like a refused configuration)."""


class StreamReader(ReconnectingReader):
    """What every streaming IMU driver shares (Xsens, VectorNav, declarative frame): the reader
    thread's batched reads, the offset learning after the first configuration, the wait in
    ``read`` for the stream to reach the rig clock, and the context manager. A subclass sets
    ``link``, ``clock``, ``rate_hz``, ``timeout_s``, ``learn_s``, ``align_wait_s``,
    ``batch_wait_s``, ``offset``, ``_cond`` and implements ``_feed(data)`` (decode, store;
    while ``_learning`` it lowers ``offset`` to the minimum of arrival - newest device time) and
    ``_latest_run_time()``."""

    _learning = False
    _chunks = 0
    offset_corrections = 0
    restamp_dropped = 0
    _last_stamp: float | None = None

    def connect(self) -> None:
        """Start the reader thread; return once the device streams (raise if it cannot)."""
        self._start_reader(10 * self.timeout_s + self.learn_s + 2.0, f"no stream from {self.link.url}")

    def _pump(self) -> None:
        data = self.link.read_some(0.05)
        wait = max(self.batch_wait_s, BURST_WAIT_S if len(data) >= BURST_BYTES else 0.0)
        if data and wait > 0:               # gather more before decoding
            buf, end = bytearray(data), time.monotonic() + wait
            while len(buf) < BURST_MAX and (left := end - time.monotonic()) > 0:
                more = self.link.read_some(left)
                if not more:
                    break
                buf += more
            data = bytes(buf)
        if data:
            self._feed(data)

    def _feed(self, data: bytes) -> None:  # pragma: no cover - subclass duty
        raise NotImplementedError

    def _latest_run_time(self) -> float | None:  # pragma: no cover - subclass duty
        """Run time of the newest stored sample (None before the first)."""
        raise NotImplementedError

    #: a lowering of the offset after the learning window must be confirmed: the estimate comes
    #: from a sample whose device time continues the CONFIRM_RUN - 1 samples before it by one
    #: sample period each (within a quarter period)
    CONFIRM_RUN = 3
    offset_unconfirmed = 0
    _recent_dev: np.ndarray | None = None

    def _track_offset(self, arrival: float, t_dev: np.ndarray) -> None:
        """Lower ``offset`` to the estimate from a chunk that arrived at rig time ``arrival`` with
        samples at device times ``t_dev`` (s, in order): arrival - the newest device time.

        The offset is the lower envelope of the chunks' apparent latencies, kept up for the whole
        run, not only over the learning window: a chunk that arrives late (the device or the
        emulator stalled, the host was busy) can only make the estimate larger, so one stall that
        covers the whole learning window at connect would otherwise put every stamp of the run
        late by the stall. After the learning window the offset is lowered only by more than
        :meth:`_correction_min_s` (20 ms of wall time in rig time): a lowering drops the samples
        it would stamp before one already handed out, and a counter gap pauses the run, so the
        ordinary jitter of the window's minimum (a few ms of wall time) stays as before. A
        lowering after the window is counted (``offset_corrections``) and logged.

        Plausibility: a frame whose checksum passes with a corrupted time field (an 8-bit sum
        misses about 1 in 256 frames with two byte errors) gives an estimate too low by the
        corruption. After the learning window the estimate is therefore taken from the newest
        sample whose device time continues the :attr:`CONFIRM_RUN` - 1 samples before it (across
        chunks) by one sample period each; a chunk whose newest time is not so confirmed is
        counted (``offset_unconfirmed``), and lowers the offset only through an older sample of
        it that is."""
        t_dev = np.asarray(t_dev, dtype=float)
        t_dev = t_dev[np.isfinite(t_dev)]
        if not t_dev.size:
            return
        n, prev = self.CONFIRM_RUN, self._recent_dev
        if n > 1:
            tail = t_dev[-(n - 1):]
            self._recent_dev = tail if prev is None or tail.size == n - 1 else \
                np.concatenate((prev, tail))[-(n - 1):]
        est = arrival - float(t_dev[-1])
        if self.offset is None:
            if self._learning:  # the first estimate comes only from the learning window
                self.offset = est
            return
        if self._learning:
            self.offset = min(self.offset, est)
            return
        if self.offset - est <= self._correction_min_s():
            return
        if n > 1:
            est = self._confirmed_estimate(arrival, t_dev, prev)
            if est is None or self.offset - est <= self._correction_min_s():
                return
        self.offset_corrections += 1
        log.warning("%s: time offset lowered by %.6f s (the chunks of the learning window arrived "
                    "late)", self.name, self.offset - est)
        self.offset = est

    def _confirmed_estimate(self, arrival: float, t_dev: np.ndarray, prev: np.ndarray | None) -> float | None:
        """arrival - the device time of the chunk's newest sample that continues the
        CONFIRM_RUN - 1 samples before it (``prev``: the last ones of earlier chunks) by one
        sample period each; None when there is none. Counts ``offset_unconfirmed`` when the
        newest sample is not confirmed."""
        n = self.CONFIRM_RUN
        h = t_dev if prev is None else np.concatenate((prev, t_dev))
        step_ok = np.abs(np.diff(h) * self.rate_hz - 1.0) < 0.25
        j, first = h.size - 1, max(h.size - t_dev.size, n - 1)
        while j >= first and not step_ok[j - n + 1:j].all():
            j -= 1
        if j < h.size - 1 or j < first:     # the newest time is not confirmed
            self.offset_unconfirmed += 1
        return arrival - float(h[j]) if j >= first else None

    def _correction_min_s(self) -> float:
        """Smallest lowering of the offset applied after the learning window, s of rig time: 20 ms
        of wall time (2 s at 100x), at least two sample periods."""
        return max(0.02 * float(getattr(self.clock, "speed", 1.0)), 2.0 / self.rate_hz)

    def _monotone(self, stamp: np.ndarray) -> np.ndarray:
        """Mask of the stamps after the last one handed out (and remember the newest): after the
        offset was lowered, samples that would be stamped at or before a sample already handed out
        are dropped and counted (``restamp_dropped``), so ``ImuBlock.time`` keeps increasing."""
        last = self._last_stamp
        keep = np.ones(stamp.size, dtype=bool) if last is None else stamp > last
        self.restamp_dropped += int(stamp.size - np.count_nonzero(keep))
        if keep.any():
            self._last_stamp = float(stamp[keep][-1])
        return keep

    def _finish_configure(self, no_frames: str) -> None:
        """After the device was configured: on the first configuration learn the offset for
        ``learn_s`` of wall time from the first frame on (LinkLost with ``no_frames`` if none
        came within ``link_timeout_s``, at least ``learn_s``), then mark the stream configured.

        The window starts at the first frame, not at the configuration's end: the first frames
        of a device (or of an emulator whose stream follows its physics) may take longer than
        ``learn_s`` to arrive, and a window that had none failed the connect and started the
        configuration over, each time with the same wait (the 1e6-frame test of
        tests/test_hil_faults.py: 'no stream' after 7.2 s of such tries at load 14-19)."""
        if self.offset is None:
            self._learning = True
            first_by = time.monotonic() + max(self.learn_s, float(getattr(self, "link_timeout_s", 0.0)))
            end = None
            while not self._stop.is_set():
                now = time.monotonic()
                if end is None and self.offset is not None:
                    end = now + self.learn_s        # the first frame came: learn from it on
                if now >= (first_by if end is None else end):
                    break
                data = self.link.read_some(0.02)
                if data:
                    self._feed(data)
            self._learning = False
            if self.offset is None:
                raise LinkLost(self.name, no_frames)
        if self._down_since is not None:
            log.info("%s: stream back after %.2f s", self.name, time.monotonic() - self._down_since)
        self._configured.set()

    def _wait_aligned(self) -> None:
        """With ``_cond`` held: wait (at most ``align_wait_s`` of wall time) until the newest
        sample is within 1.5 sample periods of the rig clock or the next chunk has arrived."""
        if self.align_wait_s > 0 and self._configured.is_set() and self.offset is not None:
            want = self.clock.now() - 1.5 / self.rate_hz
            deadline = time.monotonic() + self.align_wait_s
            chunks = self._chunks
            while ((latest := self._latest_run_time()) is None or latest < want) \
                    and self._chunks == chunks and (left := deadline - time.monotonic()) > 0:
                self._cond.wait(left)

    def _raise_if_down(self) -> None:
        """No data: LinkLost once the link has been down for ``link_timeout_s`` (wall)."""
        if (down := self.link_down_s()) is not None and down > self.link_timeout_s:
            with self._cond:
                for outage in self._outages:
                    outage[3] = True            # said: the outage's end raises no second LinkLost
            raise LinkLost(self.name, f"no data from {self.link.url} for {down:.1f} s (reconnecting)")

    # ------------------------------------------------------------ outages in what read hands out
    def _init_reader(self) -> None:
        super()._init_reader()
        #: link outages not yet accounted for by ``read``, oldest first: [batches of ``_pending``
        #: stored before it, time.monotonic() it began, time.monotonic() the device was configured
        #: again (None: still down), whether a read has raised LinkLost for it]
        self._outages: list[list] = []

    def _outage_began(self) -> None:
        with self._cond:        # after _on_link_lost: the frames cut by the loss are stored before it
            self._outages.append([len(self._pending), self._down_since, None, False])

    def _outage_ended(self, down_since: float, up_at: float) -> None:
        with self._cond:
            for outage in self._outages:
                if outage[2] is None:
                    outage[2] = up_at

    def _take_pending(self) -> list:
        """With ``_cond`` held: the stored batches ``read`` hands out now (taken from
        ``_pending``), in the order of the link's history, whenever the engine reads.

        The batches stored before a link outage go out on their own; then, while the link is down,
        none (``read`` raises LinkLost once it has been down for ``link_timeout_s``); once the
        device is configured again, a read raises LinkLost for an outage longer than
        ``link_timeout_s`` that no read has reported yet, and the next ones hand out what came
        after it. So a cut link is a link loss at any pace of the reads: before, a read that came
        only after the reconnect (a loaded host: the engine's thread held off for the whole
        outage) returned the frames from both sides of it in one block, and the engine paused on
        'IMU data gap: N samples missing inside a read' without ever seeing the link lost."""
        while self._outages:
            before, down_since, up_at, said = self._outages[0]
            if before > 0:
                taken, self._pending = self._pending[:before], self._pending[before:]
                for outage in self._outages:
                    outage[0] -= before
                return taken
            if up_at is None:
                return []
            self._outages.pop(0)
            if up_at - down_since > self.link_timeout_s and not said:
                raise LinkLost(self.name, f"link to {self.link.url} lost for {up_at - down_since:.1f} s "
                                          "(reconnected since)")
        taken, self._pending = self._pending, []
        return taken

    def _put_back(self, batch) -> None:
        """With ``_cond`` held: ``batch``, taken by :meth:`_take_pending`, goes back first."""
        self._pending.insert(0, batch)
        for outage in self._outages:
            outage[0] += 1

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class StreamImu(StreamReader):
    config_error = StreamImuConfigError
    protocol = ""

    def __init__(self, url: str, rate_hz: float, clock: Clock, *, baudrate: int, timeout_s: float,
                 align_wait_s: float, link_timeout_s: float, learn_s: float = 0.2, name: str = "imu") -> None:
        self.rate_hz, self.clock, self.name = float(rate_hz), clock, name
        self.link = SerialLink(url, name, baudrate=baudrate, timeout_s=timeout_s)
        self.timeout_s, self.align_wait_s, self.link_timeout_s, self.learn_s = \
            timeout_s, align_wait_s, link_timeout_s, learn_s
        self.batch_wait_s = 0.02 / float(getattr(clock, "speed", 1.0))
        self.stream = self._new_stream()
        self.offset: float | None = None
        self.incomplete_frames = 0
        self.configurations = 0
        self.dropped_samples = 0
        self.out_of_order = 0
        self.identity: dict[str, str] = {"device_id": "", "protocol": self.protocol}
        self._t0: float | None = None
        self._last_t: float | None = None
        self._pending: list[tuple[np.ndarray, ...]] = []
        self._latest_t: float | None = None
        self._cond = threading.Condition()
        self._learning = False
        self._chunks = 0
        #: device-time shift (s) added after a device restart, so its timeline continues
        self._shift = 0.0
        self._shift_floor = 0.0
        self._rebase_pending = False
        #: after a restart: the new samples, held until the shift is learnt (rig time _held_until)
        self._held: list[tuple[np.ndarray, ...]] | None = None
        self._held_until = 0.0
        #: external events the device time-stamps (VectorNav SYNC_IN): device time + shift, with
        #: those of a held restart epoch apart until the shift is learnt
        self._events: list[float] = []
        self._held_events: list[float] = []
        self.device_restarts = 0
        self._init_reader()
        self._last_warn = 0.0
        self._warned_bad = 0

    # ---------------------------------------------------------------- subclass duties
    def _new_stream(self):  # pragma: no cover - subclass duty
        raise NotImplementedError

    def _device_time(self, out: dict) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def _inertial(self, out: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
        raise NotImplementedError

    def _configure_device(self) -> None:
        """Commands and identity on a (re)connect; the default sends nothing."""

    def _device_events(self, out: dict) -> np.ndarray:
        """Device times (s, as ``_device_time``) of external events the frames report (e.g. a
        VectorNav's SYNC_IN edges); none by default."""
        return np.empty(0)

    # -------------------------------------------------------------------- reader thread
    def _on_link_lost(self) -> None:
        with self._cond:            # decode and store as one step (see _feed)
            out = self.stream.flush()
            self._store(out, None)

    def _feed(self, data: bytes) -> None:
        arrival = self.clock.now()
        # decoding counts the frames and storing makes them readable: one step under the lock
        # that ``counters`` and ``read`` take, so no snapshot of the counters ever includes
        # frames that ``read`` cannot yet return
        with self._cond:
            out = self.stream.feed(data)
            self._store(out, arrival)
        c = self.stream.counters
        bad = c.bad_frames + c.truncated_frames + self.out_of_order
        if bad != self._warned_bad and time.monotonic() - self._last_warn > 1.0:
            self._last_warn, self._warned_bad = time.monotonic(), bad
            log.warning("%s: %d bad, %d truncated, %d out-of-order frames, %d dropped samples so far", self.name,
                        c.bad_frames, c.truncated_frames, self.out_of_order, self.dropped_samples)

    def _store(self, out: dict, arrival: float | None) -> None:
        if not len(out.get("offset", ())):
            if arrival is None:
                self._release_held()
            return
        t_raw = self._device_time(out)
        acc, gyr, temp = self._inertial(out)
        last = self._last_t
        if self._rebase_pending and t_raw.size and arrival is not None:
            self._rebase_pending = False
            if last is not None and self.offset is not None and (
                    float(t_raw[0]) + self._shift <= last
                    or float(t_raw[0]) + self._shift + self.offset > arrival + self._ahead_tolerance()):
                self._start_rebase(t_raw, arrival, last)
        elif self._held is not None and arrival is not None and t_raw.size and np.isfinite(t_raw[-1]):
            self._lower_shift(arrival - self.offset - float(t_raw[-1]))
        t = t_raw + self._shift
        ev = self._device_events(out)
        if ev.size:
            (self._held_events if self._held is not None else self._events).extend((ev + self._shift).tolist())
        last = self._last_t
        fast = t.size > 0 and bool(np.isfinite(t).all()) and (t.size < 2 or bool(np.all(np.diff(t) > 0))) \
            and (last is None or t[0] > last)
        if fast:
            keep = np.ones(t.size, dtype=bool)
            last = float(t[-1])
        else:       # reject frames whose time does not advance (a replay, a restart mid-stream)
            keep = np.zeros(t.size, dtype=bool)
            for i, ti in enumerate(t.tolist()):
                if np.isfinite(ti) and (last is None or ti > last):
                    keep[i], last = True, ti
                else:
                    self.out_of_order += 1
        self._last_t = last
        if not keep.all():
            t, acc, gyr, temp = t[keep], acc[keep], gyr[keep], temp[keep]
        if t.size and self._held is not None:
            self._held.append((t, acc, gyr, temp))
        elif t.size:
            if self._t0 is None:
                self._t0 = float(t[0])
            if arrival is not None:
                self._track_offset(arrival, t)
            self._append(t, acc, gyr, temp)
        if self._held is not None and (arrival is None or arrival >= self._held_until):
            self._release_held()

    def _append(self, t, acc, gyr, temp) -> None:
        prev = self._latest_t
        steps = np.rint(np.diff(np.concatenate(([prev], t)) if prev is not None else t) * self.rate_hz)
        self.dropped_samples += int(np.maximum(steps - 1, 0).sum())
        with self._cond:
            self._pending.append((t, acc, gyr, temp))
            self._latest_t = float(t[-1])
            self._chunks += 1
            self._cond.notify_all()

    # Restart rebase. The device time restarted while the link was down (a USB sensor power-cycles
    # with its cable): its new timeline is shifted onto the old one. The shift is learnt as the
    # offset was on the first connect: the minimum over the chunks arriving during ``learn_s``
    # (scaled to rig time) of (arrival - offset - newest device time), never below what keeps the
    # times increasing across the outage. Until then the new samples are held back (and moved down
    # with each lower estimate), so no stamp handed out leads the clock: a single chunk's latency
    # (issue 22: the first chunk after a reconnect arrives late) would put every later stamp of the
    # run ahead of its arrival by the difference to the minimum latency.
    def _start_rebase(self, t_raw: np.ndarray, arrival: float, last: float) -> None:
        self._shift_floor = last - float(t_raw[0]) + 1.0 / self.rate_hz
        self._shift = max(arrival - self.offset - float(t_raw[-1]), self._shift_floor)
        self._held = []
        self._held_until = arrival + self.learn_s * float(getattr(self.clock, "speed", 1.0))
        self.device_restarts += 1

    #: a device time after a reconnect that would stamp its first sample more than this after its
    #: arrival (rig time; and more than REBASE_AHEAD_WALL_S of wall time at the clock's speed) did
    #: not continue: it restarted, and a wrapping time field read its new start as a wrap (a
    #: declared u32 microsecond time from 0 again is 'ahead' by up to 71 minutes)
    REBASE_AHEAD_S, REBASE_AHEAD_WALL_S = 1.0, 0.05

    def _ahead_tolerance(self) -> float:
        return max(self.REBASE_AHEAD_S, self.REBASE_AHEAD_WALL_S * float(getattr(self.clock, "speed", 1.0)))

    def _lower_shift(self, est: float) -> None:
        new = max(est, self._shift_floor)
        if new < self._shift:
            d, self._shift = self._shift - new, new
            self._last_t -= d
            self._held = [(t - d, *rest) for t, *rest in self._held]
            self._held_events = [e - d for e in self._held_events]

    def _release_held(self) -> None:
        held, self._held = self._held, None
        with self._cond:
            self._events.extend(self._held_events)
        self._held_events = []
        if not held:
            return
        log.warning("%s: the device time restarted during the outage; its timeline continues from the "
                    "reconnect (shift %.6f s)", self.name, self._shift)
        self._append(*(np.concatenate(parts) for parts in zip(*held)))

    def _configure(self) -> None:
        first = self.offset is None
        self._rebase_pending = self.configurations > 0
        self.link.ensure()
        if first:
            self.link.drain_input()
        self._configure_device()
        self.configurations += 1
        self._finish_configure(f"no {self.protocol} frames from {self.link.url}")

    def _discard_preconfig(self) -> None:
        """Forget what was decoded before our first configuration."""
        with self._cond:
            self._pending.clear()
            self._latest_t = None
        self._t0, self._last_t, self._held = None, None, None
        self.stream = self._new_stream()

    # ------------------------------------------------------------------------------ Imu
    def read(self) -> ImuBlock:
        if self._fatal is not None:
            raise self._fatal
        with self._cond:
            self._wait_aligned()
            batches = self._take_pending()
        if not batches:
            self._raise_if_down()
            return ImuBlock.empty()
        t = np.concatenate([b[0] for b in batches])
        acc = np.concatenate([b[1] for b in batches])
        gyr = np.concatenate([b[2] for b in batches])
        temp = np.concatenate([b[3] for b in batches])
        ok = np.isfinite(acc).all(axis=1) & np.isfinite(gyr).all(axis=1)
        if not ok.all():
            self.incomplete_frames += int((~ok).sum())
            t, acc, gyr, temp = t[ok], acc[ok], gyr[ok], temp[ok]
        stamp = t + (self.offset or 0.0)
        # never hand out a sample stamped after the clock: the offset is a minimum-latency estimate
        # over a learning window, and a later chunk can arrive faster than any in it; such samples
        # wait (for the estimate's error: rig-time milliseconds at most) and come with the next read
        now = self.clock.now()
        if stamp.size and stamp[-1] > now:
            cut = int(np.searchsorted(stamp, now, side="right"))
            with self._cond:
                self._put_back((t[cut:], acc[cut:], gyr[cut:], temp[cut:]))
            t, acc, gyr, temp, stamp = t[:cut], acc[:cut], gyr[:cut], temp[:cut], stamp[:cut]
        keep = self._monotone(stamp)
        if not keep.all():
            t, acc, gyr, temp, stamp = t[keep], acc[keep], gyr[keep], temp[keep], stamp[keep]
        counter = np.maximum(np.rint((t - (self._t0 or 0.0)) * self.rate_hz), 0).astype(np.uint64)
        return ImuBlock(time=stamp, counter=counter, specific_force=acc, angular_rate=gyr, temperature=temp)

    def read_events(self) -> np.ndarray:
        """Run times (s, the IMU's time base) of the device's external events since the last
        call, none stamped after ``clock.now()`` (those wait, as samples do)."""
        now = self.clock.now()
        with self._cond:
            ev = np.sort(np.asarray(self._events, float)) + (self.offset or 0.0)
            keep = ev <= now
            self._events = (ev[~keep] - (self.offset or 0.0)).tolist()
        return ev[keep]

    @property
    def counters(self) -> dict:
        """Decoder and link diagnostics (totals since connect): one consistent snapshot, in which
        every frame counted as decoded is already returned by ``read`` or waiting for it."""
        with self._cond:
            d = asdict(self.stream.counters)
            d.update(dropped_samples=self.dropped_samples, out_of_order=self.out_of_order,
                     device_restarts=self.device_restarts, offset_corrections=self.offset_corrections,
                     offset_unconfirmed=self.offset_unconfirmed, restamp_dropped=self.restamp_dropped,
                     incomplete_frames=self.incomplete_frames, link_losses=self.link.losses,
                     reconnects=self.link.reconnects, configurations=self.configurations)
        return d

    def close(self) -> None:
        """Stop the reader; then flush the decoder, so a bad frame at the very end of the stream
        (known bad only once a later frame or the end shows where it ends) is in the counters."""
        super().close()
        if self._thread is None or not self._thread.is_alive():
            self.stream.flush()

    def _latest_run_time(self) -> float | None:
        return None if self._latest_t is None else self._latest_t + self.offset


__all__ = ["BURST_BYTES", "BURST_MAX", "BURST_WAIT_S", "StreamImu", "StreamImuConfigError", "StreamImuUnitChanged",
           "StreamReader"]
