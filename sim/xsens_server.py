"""Emulated Xsens MTi on a pty: config/measurement states and an MTData2 stream.

The client opens ``server.path`` with ``serial.serial_for_url``. Supported requests: GoToConfig,
GoToMeasurement, SetOutputConfiguration (config state only; the ack echoes the applied
configuration), ReqDID (DeviceID: ``device_id`` as 4 bytes, or 8 when it does not fit 32 bits;
``device_id=None`` emulates a device without ReqDID: Error 0x04), Reset; anything else gets Error
0x04 (invalid message). A configuration
with an unknown data ID, a rate that does not divide the packet rate, or frames that do not fit
the nominal ``baudrate`` (8N1) is refused with Error 0x21 (invalid parameter) and the reason in
``last_error``.

Samples come from ``source(t) -> dict`` called with a vector of sample times t (s, on the shared
clock): keys acceleration (n,3) m/s^2, rate_of_turn (n,3) rad/s, temperature (n,) degC and
optionally status_word (n,), delta_v (n,3) m/s, delta_q (n,4). Sample k of a measurement period
is taken at t0 + k / rate; PacketCounter counts every emitted packet (u16, wraps) and
SampleTimeFine = stf_offset + round((t - t_origin) * 10 kHz) (u32, wraps).

Fault injection (side channel): ``byte_error_rate`` XORs random non-zero values into outgoing
bytes (seeded); ``frames_hit`` counts the MTData2 frames that received at least one error;
``go_to_config_delay_s`` holds a GoToConfig back (the stream goes on) for that many wall seconds.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from rigctl.drivers.xsens import (FREQ_MAX, MID, SAMPLE_TIME_FINE_HZ, XDI, XDI_FIELD, ErrorCode, OutputItem,
                                  RateDoesNotFitError, XsensError, ack_for, build_message,
                                  decode_output_configuration, encode_device_id, encode_mtdata2, resolve_output_rate,
                                  encode_output_configuration,
                                  error_message, item_size, mtdata2_frame_bytes, split_messages, split_xdi)

from .links import FlowPtyEndpoint

DEFAULT_CONFIG = [OutputItem(XDI.PACKET_COUNTER, FREQ_MAX), OutputItem(XDI.SAMPLE_TIME_FINE, FREQ_MAX),
                  OutputItem(XDI.ACCELERATION, 100), OutputItem(XDI.RATE_OF_TURN, 100),
                  OutputItem(XDI.TEMPERATURE, 100), OutputItem(XDI.STATUS_WORD, 100)]
MAX_BATCH = 20000


def still_source(t: np.ndarray) -> dict[str, np.ndarray]:
    """A sensor at rest, z up: specific force (0, 0, 9.80665) m/s^2, zero rate, 25 degC."""
    n = len(t)
    return {"acceleration": np.tile([0.0, 0.0, 9.80665], (n, 1)), "rate_of_turn": np.zeros((n, 3)),
            "temperature": np.full(n, 25.0), "status_word": np.zeros(n, dtype=np.int64),
            "delta_v": np.zeros((n, 3)), "delta_q": np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))}


def check_output_fits(items: list[OutputItem], max_rate_hz: int, baudrate: int, bits_per_byte: int = 10) -> int:
    """Packet rate (Hz) of a configuration, after checking it is valid and fits ``baudrate``.

    Bit rate = bits_per_byte * (5 * R + sum_i (3 + size_i) * f_i) for packet rate R and item
    rates f_i (every f_i must divide R; FREQ_MAX items are in every packet). Raises XsensError /
    RateDoesNotFitError.
    """
    if not items:
        raise XsensError("empty output configuration")
    for it in items:
        if item_size(it.xdi) is None or split_xdi(it.xdi)[0] not in XDI_FIELD:
            raise XsensError(f"unsupported data ID 0x{it.xdi:04X}")
        if it.freq_hz not in (0, FREQ_MAX) and not 0 < it.freq_hz <= max_rate_hz:
            raise XsensError(f"0x{it.xdi:04X}: rate {it.freq_hz} Hz outside 1..{max_rate_hz} Hz")
    r = resolve_output_rate(items, max_rate_hz)
    rates = [r if it.freq_hz in (0, FREQ_MAX) else it.freq_hz for it in items]
    if any(r % f for f in rates):
        raise XsensError(f"item rates {rates} Hz must all divide the packet rate {r} Hz")
    need = bits_per_byte * (5 * r + sum((3 + item_size(it.xdi)) * f for it, f in zip(items, rates)))
    if need > baudrate:
        full = mtdata2_frame_bytes([it.xdi for it in items])
        raise RateDoesNotFitError(
            f"output configuration needs {need:,} bit/s (up to {full} bytes/frame at {r} Hz), more than "
            f"the {baudrate:,} baud line carries; lower the rate, drop fields or raise the baud rate")
    return r


class XsensServer:
    """Xsens MTi emulator on a pty; ``path`` is the client's port; ``close()`` stops it."""

    def __init__(self, source: Callable[[np.ndarray], dict] = still_source,
                 clock: Callable[[], float] | None = None, baudrate: int = 921_600, max_rate_hz: int = 2000,
                 device_id: int | None = 0x03780001, stf_offset: int = 0, byte_error_rate: float = 0.0,
                 seed: int = 0, start_in_measurement: bool = False) -> None:
        self.source, self.baudrate, self.max_rate_hz = source, baudrate, max_rate_hz
        t_wall0 = time.monotonic()
        self.clock = clock if clock is not None else (lambda: time.monotonic() - t_wall0)
        self.t_origin = self.clock()
        self.device_id, self.stf_offset = device_id, stf_offset
        self.byte_error_rate, self._rng = byte_error_rate, np.random.default_rng(seed)
        #: wall seconds a GoToConfig received in measurement mode takes to take effect (and be
        #: acknowledged), the unit streaming on meanwhile: a unit slow to leave measurement mode
        self.go_to_config_delay_s = 0.0
        self.config = list(DEFAULT_CONFIG)
        self.rate_hz = check_output_fits(self.config, max_rate_hz, baudrate)
        self.state = "config"
        self.counter = 0
        self.frames_sent = 0
        self.frames_hit = 0
        self.last_error = ""
        self._k = 0
        self._t0 = 0.0
        self._buf = b""
        self._lock = threading.Lock()
        self._stop = threading.Event()
        # flow control: the emulator streams faster than the nominal baud rate (20x, 100x), so a
        # port that dropped what did not fit (13.8 kB) lost frames whenever the client paused
        # for 60 ms at 200 Hz and 20x (test_wire_xsens_server at load 19: 65 frames)
        self.port = FlowPtyEndpoint(self._on_data, name="xsens-pty")
        self.path = self.port.path
        if start_in_measurement:
            self._enter_measurement()
        self._thread = threading.Thread(target=self._stream, name="xsens-stream", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------------ requests
    def _on_data(self, data: bytes, write: Callable[[bytes], None]) -> None:
        self._buf += data
        msgs, used, _bad = split_messages(self._buf)
        self._buf = self._buf[used:]
        for m in msgs:
            if m.mid == MID.GO_TO_CONFIG and self.go_to_config_delay_s > 0 and self.state == "measurement":
                time.sleep(self.go_to_config_delay_s)     # streaming on meanwhile (_stream)
            write(self._handle(m.mid, m.data))

    def _enter_measurement(self) -> None:
        self._t0, self._k = self.clock(), 0
        self.state = "measurement"

    def _handle(self, mid: int, data: bytes) -> bytes:
        with self._lock:
            if mid == MID.GO_TO_CONFIG:
                self.state = "config"
                return ack_for(mid)
            if mid == MID.GO_TO_MEASUREMENT:
                self._enter_measurement()
                return ack_for(mid)
            if mid == MID.REQ_DID and self.device_id is not None:
                return build_message(MID.DEVICE_ID, encode_device_id(self.device_id))
            if mid == MID.RESET:
                self.state = "config"
                return ack_for(mid)
            if mid == MID.SET_OUTPUT_CONFIGURATION and self.state == "config":
                try:
                    items = decode_output_configuration(data)
                    rate = check_output_fits(items, self.max_rate_hz, self.baudrate)
                except (XsensError, RateDoesNotFitError) as exc:
                    self.last_error = str(exc)
                    return error_message(ErrorCode.INVALID_PARAMETER)
                self.config, self.rate_hz = items, rate
                return ack_for(mid, encode_output_configuration(items))
            self.last_error = f"message 0x{mid:02X} not accepted in {self.state} state"
            return error_message(ErrorCode.INVALID_MESSAGE)

    def power_cycle(self) -> None:
        """The MTi restarts (its power lost and back, not a cable pull): SampleTimeFine and
        PacketCounter start again from 0 now (``stf_offset`` moves its time base), and it waits
        in config state for its client to configure it again (an MTi powers up streaming its
        stored configuration; a driver reconfigures on every reconnect either way)."""
        with self._lock:
            self.stf_offset = -int(round((self.clock() - self.t_origin) * SAMPLE_TIME_FINE_HZ))
            self.counter = 0
            self.state = "config"

    # ------------------------------------------------------------------------ streaming
    def _stream(self) -> None:
        while not self._stop.wait(0.002):
            with self._lock:
                if self.state != "measurement":
                    continue
                n_due = int(np.floor((self.clock() - self._t0) * self.rate_hz)) + 1 - self._k
                n = min(max(n_due, 0), MAX_BATCH)
                if n == 0:
                    continue
                k = self._k + np.arange(n)
                self._k += n
                frames = self._encode(k)
            self.port.write(frames)

    def _encode(self, k: np.ndarray) -> bytes:
        t = self._t0 + k / self.rate_hz
        f = self.source(t)
        n = len(k)
        f = dict(f)
        f["packet_counter"] = self.counter + np.arange(n)
        f["sample_time_fine"] = self.stf_offset + np.round((t - self.t_origin) * SAMPLE_TIME_FINE_HZ).astype(np.int64)
        f.setdefault("status_word", np.zeros(n, dtype=np.int64))
        self.counter += n
        divs = [1 if it.freq_hz in (0, FREQ_MAX) else self.rate_hz // it.freq_hz for it in self.config]
        pattern = np.stack([(k % d) == 0 for d in divs], axis=1)
        keys, inv = np.unique(pattern, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        chunks: list[np.ndarray] = [np.empty(0, np.uint8)] * n
        if len(keys) == 1:
            xdis = [it.xdi for it, on in zip(self.config, keys[0]) if on]
            arr = encode_mtdata2(xdis, f)
            out, flen = arr.reshape(-1), np.full(n, arr.shape[1])
        else:
            for g, key in enumerate(keys):
                rows = np.flatnonzero(inv == g)
                xdis = [it.xdi for it, on in zip(self.config, key) if on]
                enc = encode_mtdata2(xdis, {kk: np.asarray(v)[rows] for kk, v in f.items()})
                for r, fr in zip(rows.tolist(), enc):
                    chunks[r] = fr
            out = np.concatenate(chunks)
            flen = np.array([c.size for c in chunks])
        bounds = np.cumsum(flen)
        if self.byte_error_rate > 0:
            out = out.copy()
            pos = np.flatnonzero(self._rng.random(out.size) < self.byte_error_rate)
            out[pos] ^= self._rng.integers(1, 256, pos.size).astype(np.uint8)
            self.frames_hit += int(np.unique(np.searchsorted(bounds, pos, side="right")).size)
        self.frames_sent += n
        return out.tobytes()

    def close(self) -> None:
        self._stop.set()
        self.port.abort_writes()            # the stream thread may wait for its client
        self._thread.join(timeout=5)
        self.port.close()

    def __enter__(self) -> XsensServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
