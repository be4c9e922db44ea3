"""Emulated VectorNav VN-100 on a pty: the ASCII register protocol and the binary output stream.

Requests (``$VN...*CK\\r\\n``, checksum checked unless ``XX``): ``VNRRG`` of register 1 (model),
3 (serial number), 4 (firmware), 6 (async ASCII type), 75 (binary output 1); ``VNWRG`` of 6,
75 and 76 / 77 (binary outputs 2 and 3: stored, not streamed). The reply echoes the register (``$VNRRG,03,0100012345*CK``, ``$VNWRG,75,1,8,05,2001,001C*CK``);
errors are ``$VNERR,<code>``: 3 bad checksum, 4 unknown command, 7 invalid parameter (a layout
with an undefined field or a divisor of 0), 8 unknown register, 12 insufficient baud rate (the
frames at the requested rate need more than the nominal ``baudrate``, 10 bits per byte).

Binary output 1 streams while its AsyncMode is non-zero, at 800 Hz / RateDivisor, on the
world's sample grid; TimeStartup = (t - t_origin) in ns + ``startup_ns`` (the sensor powered up
before the emulator's clock started); SyncInCnt counts the edges given to :meth:`syncin` (rig
times: a tap switch or PPS wired to SYNC_IN; :meth:`Hardware.pulse` gives them too) up to each
frame's time since the sensor powered up, TimeSyncIn the ns since the newest of them (since
power-up before the first).
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from rigctl.drivers import vectornav as V

from .stream_twin import StreamTwin


class VectorNavServer(StreamTwin):
    def __init__(self, source, clock: Callable[[], float], *, baudrate: int = 921_600,
                 serial_number: str = "0100012345", model: str = "VN-100T-CR", firmware: str = "2.1.0.0",
                 startup_ns: int = 12_345_678_901, seed: int = 0) -> None:
        self.baudrate, self.serial_number, self.model, self.firmware = baudrate, serial_number, model, firmware
        self.startup_ns = int(startup_ns)
        self.async_mode, self.divisor = 0, 8
        self.layout = V.Layout.of({1: 0x0001})
        self.ascii_type = 14
        #: binary outputs 2 and 3 (registers 76, 77): (AsyncMode, RateDivisor, layout); the
        #: emulator keeps them but streams only output 1
        self.other_outputs: dict[int, tuple[int, int, V.Layout]] = {}
        self.last_error = ""
        self._buf = b""
        #: SYNC_IN edges (rig times, sorted) and the index of the first since power-up
        self.syncin_times: list[float] = []
        self._syncin_base = 0
        super().__init__(source, clock, V.IMU_RATE_HZ / self.divisor, seed=seed, name="vectornav-pty")

    # ------------------------------------------------------------------------ requests
    def _on_data(self, data: bytes, write: Callable[[bytes], None]) -> None:
        self._buf += data
        while b"\n" in self._buf:
            line, self._buf = self._buf.split(b"\n", 1)
            line = line.strip()
            if line.startswith(b"$"):
                # the reply goes out before the first frame of an output it switched on, as from
                # a sensor: the IMU stream thread encodes frames under the same lock
                with self._lock:
                    write(self._handle(line))
        if len(self._buf) > 4096:
            self._buf = b""

    def _err(self, code: int, why: str) -> bytes:
        self.last_error = why
        return V.command(f"VNERR,{code:02d}")

    def _handle(self, line: bytes) -> bytes:
        try:
            head, fields = V.parse_line(line)
        except V.VectorNavError as exc:
            return self._err(3, str(exc))
        if head not in ("VNRRG", "VNWRG") or not fields or not fields[0].isdigit():
            return self._err(4, f"unknown command {head}")
        reg = int(fields[0])
        with self._lock:
            if head == "VNWRG":
                if reg == 6 and len(fields) == 2 and fields[1].isdigit():
                    self.ascii_type = int(fields[1])
                elif reg in (76, 77):           # binary outputs 2 and 3: kept, never streamed here
                    try:
                        mode, div, layout = V.Layout.from_register(fields[1:])
                    except V.VectorNavError as exc:
                        return self._err(7, str(exc))
                    self.other_outputs[reg] = (mode, div, layout)
                elif reg == 75:
                    try:
                        mode, div, layout = V.Layout.from_register(fields[1:])
                    except V.VectorNavError as exc:
                        return self._err(7, str(exc))
                    if div < 1 or mode not in (0, 1, 2, 3):
                        return self._err(7, f"AsyncMode {mode} / RateDivisor {div}")
                    rate = V.IMU_RATE_HZ / div
                    if mode and 10 * layout.length * rate > self.baudrate:
                        return self._err(12, f"{layout.length}-byte frames at {rate:g} Hz need "
                                             f"{10 * layout.length * rate:,.0f} bit/s > {self.baudrate:,}")
                    self.async_mode, self.divisor, self.layout, self.rate_hz = mode, div, layout, rate
                    if mode:
                        self._enter_measurement()
                    else:
                        self.state = "config"
                else:
                    return self._err(8, f"register {reg} is not writable here")
                return V.command(",".join(["VNWRG", f"{reg:02d}", *fields[1:]]))
            values = {1: self.model, 3: self.serial_number, 4: self.firmware, 6: str(self.ascii_type),
                      75: ",".join(self.layout.register_values(self.async_mode, self.divisor)),
                      **{r: ",".join(lay.register_values(m, d)) for r, (m, d, lay) in self.other_outputs.items()}}
            if reg not in values:
                return self._err(8, f"register {reg} is not emulated")
            return V.command(f"VNRRG,{reg:02d},{values[reg]}")

    def syncin(self, t: float) -> None:
        """An edge on SYNC_IN at rig time ``t``."""
        import bisect
        with self._lock:
            bisect.insort(self.syncin_times, float(t))

    def power_cycle(self) -> None:
        """The sensor restarts (a USB cable pulled): TimeStartup starts again from 0, the binary
        output is off until configured again."""
        with self._lock:
            self.startup_ns = -int(round((self.clock() - self.t_origin) * 1e9))
            self.async_mode, self.state = 0, "config"
            self._syncin_base = int(np.searchsorted(self.syncin_times, self.clock(), side="right"))

    # ------------------------------------------------------------------------ frames
    def _frames(self, k: np.ndarray, t: np.ndarray, src: dict) -> np.ndarray:
        ns = self.startup_ns + np.rint((t - self.t_origin) * 1e9).astype(np.int64)
        edges = np.asarray(self.syncin_times[self._syncin_base:], float)
        count = np.searchsorted(edges, t, side="right")
        since_ns = ns
        if edges.size:
            newest = edges[np.maximum(count - 1, 0)]
            since_ns = np.where(count > 0, np.rint((t - newest) * 1e9).astype(np.int64), ns)
        fields = {"time_startup_ns": ns, "time_syncin_ns": since_ns, "syncin_count": count,
                  "uncomp_accel": src["acceleration"], "uncomp_gyro": src["rate_of_turn"],
                  "accel": src["acceleration"], "angular_rate": src["rate_of_turn"],
                  "temperature": src["temperature"]}
        return V.encode(self.layout, fields)


__all__ = ["VectorNavServer"]
