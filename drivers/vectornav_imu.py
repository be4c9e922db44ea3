"""VectorNav VN-100/200/300 driver (binary output over a serial port) behind the engine's
:class:`rigctl.devices.Imu`; the protocol is :mod:`rigctl.drivers.vectornav`.

On every (re)connect, over the ASCII protocol (each command checked against its reply, three
tries): binary output 1 off (``$VNWRG,75,0,...``) and asynchronous ASCII output off
(``$VNWRG,06,0``) so the line goes quiet; the identity (registers 1 model, 3 serial number, 4
firmware version); then binary output 1 on serial port 1 at ``800 / rate_hz`` (the RateDivisor
of the 800 Hz ImuRate; a rate that does not divide 800 Hz is refused) with group 1 TimeStartup
and SyncInCnt and group 3 UncompAccel, UncompGyro and Temp -- the sensor's calibrated but
uncompensated measurements, which is what a calibration wants. A ``$VNERR`` reply (e.g. 12:
insufficient baud rate) raises :class:`VectorNavConfigError` from :meth:`connect`.

Time base: device time = TimeStartup (ns since the sensor started, u64: no wrap) / 1e9 s, mapped
onto the run clock as in :mod:`rigctl.drivers.stream_imu`.

SYNC_IN: each frame carries SyncInCnt and TimeSyncIn (ns since the newest SYNC_IN edge); an edge is
the frame where the count advances, at TimeStartup - TimeSyncIn, on the same time base as the
samples. :class:`VectorNavSyncIn` hands them to the engine as pulses (``pulses: {driver:
vectornav}``), recorded in ``/pulses`` with source ``vectornav``.

Identity: ``{"device_id": <serial number>, "model": ..., "firmware": ..., "protocol":
"VectorNav binary"}``; after a reconnect a different serial number stops the reader with
:class:`VectorNavUnitChanged` (nothing of the other unit is recorded).
"""
from __future__ import annotations

import logging
import time

import numpy as np

from rigctl.devices import LinkLost, Pulses

from . import vectornav as V
from .stream_imu import StreamImu, StreamImuConfigError, StreamImuUnitChanged

log = logging.getLogger(__name__)
PROTOCOL = "VectorNav binary"
#: group 1: TimeStartup (bit 0), TimeSyncIn (bit 2), SyncInCnt (bit 13); group 3: UncompAccel (2),
#: UncompGyro (3), Temp (4)
LAYOUT = V.Layout.of({1: 0x0001 | 0x0004 | 0x2000, 3: 0x0004 | 0x0008 | 0x0010})


class VectorNavConfigError(StreamImuConfigError):
    """The sensor refused a command ($VNERR) or the configuration cannot be expressed."""


class VectorNavUnitChanged(StreamImuUnitChanged):
    """Another serial number on the port after a reconnect."""


def rate_divisor(rate_hz: float) -> int:
    div = V.IMU_RATE_HZ / float(rate_hz)
    if div != int(div) or not 1 <= div <= 65535:
        raise VectorNavConfigError(f"a VectorNav outputs at {V.IMU_RATE_HZ} Hz / N; {rate_hz:g} Hz is not one of "
                                   "those rates (e.g. 800, 400, 200, 100, 50 Hz)")
    return int(div)


class VectorNavImu(StreamImu):
    """VectorNav over ``url``; ``connect()`` then ``read()``; ``close()``."""

    config_error = VectorNavConfigError
    protocol = PROTOCOL

    def __init__(self, url: str, rate_hz: float, clock, *, baudrate: int = 921_600, timeout_s: float = 0.5,
                 align_wait_s: float = 0.02, link_timeout_s: float = 2.0, learn_s: float = 0.2,
                 name: str = "imu") -> None:
        self.divisor = rate_divisor(rate_hz)
        self.layout = LAYOUT
        self._rx = b""
        self.last_syncin_count = -1
        self.syncin_missed = 0
        self._syncin_prev: int | None = None
        super().__init__(url, rate_hz, clock, baudrate=baudrate, timeout_s=timeout_s, align_wait_s=align_wait_s,
                         link_timeout_s=link_timeout_s, learn_s=learn_s, name=name)

    def _new_stream(self):
        return V.decoder(self.layout)

    def _device_time(self, out: dict) -> np.ndarray:
        return out["time_startup_ns"].astype(np.float64) * 1e-9

    def _device_events(self, out: dict) -> np.ndarray:
        """SYNC_IN edges: where SyncInCnt advances from one frame to the next, the newest edge was
        TimeSyncIn ns before the frame's TimeStartup. The first frame after a (re)connect and a
        count that went back (the sensor restarted) set the baseline; a count that advanced by
        more than one between two frames lost the earlier edges' times (``syncin_missed``)."""
        if not len(out.get("syncin_count", ())) or "time_syncin_ns" not in out:
            return np.empty(0)
        cnt = out["syncin_count"].astype(np.int64)
        prev = np.concatenate(([self._syncin_prev if self._syncin_prev is not None else cnt[0]], cnt[:-1]))
        step = cnt - prev
        self._syncin_prev, self.last_syncin_count = int(cnt[-1]), int(cnt[-1])
        new = step > 0
        self.syncin_missed += int((step[new] - 1).sum())
        return (out["time_startup_ns"][new].astype(np.float64) - out["time_syncin_ns"][new].astype(np.float64)) * 1e-9

    def syncin_pulses(self) -> VectorNavSyncIn:
        """The pulse source of this sensor's SYNC_IN input (config ``pulses: {driver: vectornav}``)."""
        return VectorNavSyncIn(self)

    @property
    def counters(self) -> dict:
        d = super().counters
        d["syncin_missed"] = self.syncin_missed
        return d

    def _inertial(self, out: dict):
        return out["uncomp_accel"], out["uncomp_gyro"], out["temperature"]

    # ---------------------------------------------------------------------------- ASCII
    def _request(self, cmd: bytes, header: str, what: str, tries: int = 3, required: bool = True,
                 keep_rest: bool = False) -> list[str] | None:
        """Send ``cmd`` until its reply arrives: a line with ``header`` (e.g. ``VNRRG``) and the
        same register number, or ``$VNERR``. Returns the reply's fields; ``keep_rest``: bytes
        after the reply go to the decoder (the binary stream that follows it)."""
        want = ("$" + header).encode()
        reg = V.parse_line(cmd)[1][0] if header in ("VNRRG", "VNWRG") else None
        for _ in range(tries):
            buf = b""
            self.link.write(cmd)
            deadline = time.monotonic() + self.timeout_s
            while time.monotonic() < deadline and not self._stop.is_set():
                buf += self.link.read_some(max(1e-3, min(0.05, deadline - time.monotonic())))
                while True:
                    hits = [i for i in (buf.find(want), buf.find(b"$VNERR")) if i >= 0]
                    start = min(hits) if hits else -1
                    end = buf.find(b"\r\n", start) if start >= 0 else -1
                    if end < 0:
                        break
                    line, buf = buf[start:end], buf[end + 2:]
                    try:
                        head, fields = V.parse_line(line)
                    except V.VectorNavError as exc:
                        log.warning("%s: %s", self.name, exc)
                        continue
                    if head == "VNERR":
                        code = int(fields[0]) if fields and fields[0].isdigit() else -1
                        msg = f"{self.name}: the sensor refused {what}: error {code} ({V.ERRORS.get(code, '?')})"
                        if not required:
                            log.warning(msg)
                            return None
                        raise VectorNavConfigError(msg)
                    if reg is not None and (not fields or not fields[0].isdigit() or int(fields[0]) != int(reg)):
                        continue                    # a reply to something else (a stale request)
                    if keep_rest and buf:
                        self._feed(buf)
                    return fields
        if not required:
            log.warning("%s: no answer to %s from %s after %d tries", self.name, what, self.link.url, tries)
            return None
        raise LinkLost(self.name, f"no reply to {what} from {self.link.url}")

    def _register(self, reg: int) -> str:
        f = self._request(V.read_register(reg), "VNRRG", f"reading register {reg}", required=False)
        return ",".join(f[1:]) if f and len(f) > 1 else ""

    def identify(self) -> str:
        """Model, serial number and firmware, read over the ASCII protocol (no streaming)."""
        self.link.open()
        self.link.drain_input()
        try:
            self._request(V.write_register(75, *self.layout.register_values(0, self.divisor)), "VNWRG",
                          "binary output off")
            model, serial, fw = self._register(1), self._register(3), self._register(4)
        finally:
            self.link.close()
        return f"VectorNav {model or '?'}, serial number {serial or '?'}, firmware {fw or '?'}"

    def _configure_device(self) -> None:
        first = self.configurations == 0
        self._request(V.write_register(75, *self.layout.register_values(0, self.divisor)), "VNWRG",
                      "binary output off")
        self._request(V.write_register(6, 0), "VNWRG", "ASCII output off", required=False)
        for reg in (76, 77):        # binary outputs 2 and 3: another tool may have left them on
            self._request(V.write_register(reg, *self.layout.register_values(0, self.divisor)), "VNWRG",
                          f"binary output {reg - 74} off", required=False)
        if first:
            self._discard_preconfig()
        model, serial, fw = self._register(1), self._register(3), self._register(4)
        known = self.identity.get("device_id", "")
        if first:
            self.identity = {"device_id": serial, "model": model, "firmware": fw, "protocol": PROTOCOL}
            if not serial:
                log.warning("%s: the sensor does not report its serial number (set imu: serial: in the rig "
                            "config)", self.name)
        elif known and serial and serial != known:
            raise VectorNavUnitChanged(
                f"{self.name}: a different unit is now on {self.link.url}: serial number {serial}, but the run "
                f"started with {known}; its data are not recorded -- reconnect unit {known} and resume the run "
                "(rigctl resume), or start a new run for the other unit")
        self.stream.flush()
        self.stream = self._new_stream()
        self._syncin_prev = None                 # the count over the outage is unknown: a new baseline
        self._request(V.write_register(75, *self.layout.register_values(1, self.divisor)), "VNWRG",
                      f"the binary output ({self.rate_hz:g} Hz)", keep_rest=True)


class VectorNavSyncIn:
    """Pulses from a VectorNav's SYNC_IN input (a tap switch, a PPS wired to it): the edges the
    sensor time-stamps in its own frames (SyncInCnt, TimeSyncIn), on the IMU's time base -- so a
    lab can use the VectorNav as the tap timestamper. Read by the engine as any pulse source."""

    source = "vectornav"

    def __init__(self, imu: VectorNavImu) -> None:
        self.imu = imu

    def read(self) -> Pulses:
        t = self.imu.read_events()
        n = t.size
        return Pulses(time=t, gps_week=np.full(n, -1, np.int32), gps_seconds=np.full(n, np.nan), source=self.source)

    def identify(self) -> str:
        return "VectorNav SYNC_IN (read with the IMU)"


__all__ = ["LAYOUT", "PROTOCOL", "VectorNavConfigError", "VectorNavImu", "VectorNavSyncIn", "VectorNavUnitChanged",
           "rate_divisor"]
