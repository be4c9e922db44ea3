"""Xsens MTi driver (MT low-level protocol, MTData2) behind the engine's :class:`rigctl.devices.Imu`.

A reader thread owns the port (any pyserial URL). It configures the device -- GoToConfig,
SetOutputConfiguration (PacketCounter and SampleTimeFine in every packet; Acceleration,
RateOfTurn, Temperature, StatusWord at ``rate_hz``, float32), GoToMeasurement, each checked
against its acknowledgement -- then feeds every byte that arrives to the vectorised
:class:`~rigctl.drivers.xsens_decode.MTData2Stream`. :meth:`XsensImu.read` returns an
:class:`~rigctl.devices.ImuBlock` of everything decoded since the last call.

Bad input is counted, logged and dropped, never accepted and never fatal: corrupted,
mis-checksummed or truncated frames (``counters.bad_frames`` / ``truncated_frames``), unknown data
IDs (``unknown_xdi``), PacketCounter gaps (``dropped_samples``), counters that do not advance
(``out_of_order``: the frame is rejected), frames lacking a configured field
(``incomplete_frames``).

Time base (units s):

* device time ``t_dev = SampleTimeFine / 10 kHz`` (unwrapped; wrap ``sample_time_fine_wrap``);
* ``ImuBlock.counter = round((STF - STF_first) / (10 kHz / rate_hz))``: the sample's index on the
  device's nominal grid since the first sample, so a gap means samples that never arrived
  (dropped on the line or lost during a disconnect);
* ``ImuBlock.time = t_dev + offset``, the offset learnt while the stream starts (``learn_s`` of
  wall time) as the minimum over arriving chunks of (rig clock at arrival - t_dev of the newest
  sample in the chunk), i.e. the minimum-latency estimate, and kept tracking that lower envelope
  for the rest of the run (a stall across the learning window is corrected by the first timely
  chunk: ``offset_corrections``; samples it would stamp at or before one already handed out are
  dropped, ``restamp_dropped``); IMU times are therefore on the run's time base with an error of
  about the smallest transport latency.

``read`` first waits (at most ``align_wait_s`` of wall time) until the newest sample is within 1.5
sample periods of the rig clock or, failing that, until the next chunk of data has arrived, so
what it returns reaches up to the rig clock within one transport batch and the engine's sample
windows line up with its clock even when the rig runs many times faster than real time.

Link loss: the thread reconnects with backoff and reconfigures the device; samples of the outage
show up as a counter gap. ``read`` raises :class:`rigctl.devices.LinkLost` once the link has been
down for ``link_timeout_s`` (wall) -- the engine's cue to pause -- and returns data again after
the reconnect. A read that comes only after the reconnect (the engine held off the CPU for the
whole outage) still sees the loss in order: the frames from before the cut, then LinkLost for an
outage longer than ``link_timeout_s``, then the frames after it (StreamReader._take_pending). A configuration the device refuses (e.g. rate too high for the baud rate) raises
:class:`XsensConfigError` from :meth:`connect`.

Identity: in config mode (after GoToConfig, before the output configuration) the driver sends
ReqDID and keeps the DeviceID as :attr:`XsensImu.identity` = ``{"device_id": "03780001",
"protocol": "Xsens MT"}`` (upper-case hex, as Xsens prints it; 16 digits for an 8-byte ID). A
device that answers Error, or nothing after the usual three tries, gets ``device_id`` ``""`` and
a logged warning; the run goes on. Every reconnect reads the ID again before the device is put
back into measurement: a different ID means another unit is now on the port, and the reader
stops with :class:`XsensUnitChanged` (the fatal path of a refused configuration: ``read`` raises
it, the run ends failed with both IDs in its message, and not one sample of the other unit is
recorded). An ID unreadable on reconnect is a warning, as on the first connect.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import asdict

import numpy as np

from rigctl.devices import Clock, DeviceFault, ImuBlock, LinkLost
from rigctl.errors import InputError

from .serial_link import SerialLink
from .stream_imu import StreamReader
from .xsens import (FREQ_MAX, MID, SAMPLE_TIME_FINE_HZ, SAMPLE_TIME_FINE_WRAP, XDI, ErrorCode, OutputItem,
                    XsensError, check_rate_fits, decode_device_id, decode_output_configuration, go_to_config,
                    go_to_measurement, req_did, set_output_configuration)
from .xsens_decode import MTData2Batch, MTData2Stream

log = logging.getLogger(__name__)


class XsensConfigError(InputError, RuntimeError):
    """The device refused (or never acknowledged) the configuration of the rig config (rate,
    baud rate, output): fix the config (:class:`rigctl.errors.InputError`, exit code 2)."""


class XsensUnitChanged(DeviceFault):
    """After a reconnect the device on the port reports another DeviceID than the unit the run
    started with: a different IMU. Fatal for the reader (no sample of it is accepted)."""


PROTOCOL = "Xsens MT"


def output_items(rate_hz: int) -> list[OutputItem]:
    return [OutputItem(XDI.PACKET_COUNTER, FREQ_MAX), OutputItem(XDI.SAMPLE_TIME_FINE, FREQ_MAX),
            OutputItem(XDI.ACCELERATION, rate_hz), OutputItem(XDI.RATE_OF_TURN, rate_hz),
            OutputItem(XDI.TEMPERATURE, rate_hz), OutputItem(XDI.STATUS_WORD, rate_hz)]


class XsensImu(StreamReader):
    """Xsens MTi over ``url``; see the module docstring. ``connect()`` then ``read()``; ``close()``."""

    config_error = XsensConfigError
    #: no confirmation of offset lowerings by the samples before (StreamReader.CONFIRM_RUN): a
    #: restarted MTi (SampleTimeFine from 0) is a new time base that the decoder unwraps as a
    #: wrap (``time_restarts``), so its samples read up to 2^32 ticks (4.97 days) late; only
    #: lowering the offset at once, on the chunk that shows the jump, keeps their stamps on time
    #: (a lowering held back a chunk would let those samples out stamped days late, and every
    #: later sample would be dropped as stamped before them). A corrupted SampleTimeFine that
    #: passed the checksum no longer gets here: the decoder gives its frame no time
    #: (``time_outliers``) and keeps the reference.
    CONFIRM_RUN = 1

    def __init__(self, url: str, rate_hz: float, clock: Clock, *, baudrate: int = 921_600,
                 timeout_s: float = 0.5, sample_time_fine_wrap: int = SAMPLE_TIME_FINE_WRAP,
                 align_wait_s: float = 0.02, link_timeout_s: float = 2.0, learn_s: float = 0.2,
                 name: str = "imu") -> None:
        if rate_hz != int(rate_hz):
            raise ValueError("the Xsens output rate must be a whole number of Hz")
        self.rate_hz, self.clock, self.name = int(rate_hz), clock, name
        self.items = output_items(self.rate_hz)
        check_rate_fits([it.xdi for it in self.items], self.rate_hz, baudrate)
        self.link = SerialLink(url, name, baudrate=baudrate, timeout_s=timeout_s)
        self.timeout_s, self.align_wait_s, self.link_timeout_s, self.learn_s = \
            timeout_s, align_wait_s, link_timeout_s, learn_s
        self.stream = MTData2Stream(wrap_ticks=sample_time_fine_wrap)
        #: decode at most every ~20 ms of rig time (the decoder costs ~0.4 ms per call)
        self.batch_wait_s = 0.02 / float(getattr(clock, "speed", 1.0))
        self.ticks_per_sample = SAMPLE_TIME_FINE_HZ / self.rate_hz
        self.offset: float | None = None
        self.incomplete_frames = 0
        self.configurations = 0
        #: the unit under test: {"device_id": upper-case hex or "", "protocol": "Xsens MT"}
        self.identity: dict[str, str] = {"device_id": "", "protocol": PROTOCOL}
        self._stf0: int | None = None
        self._pending: list[MTData2Batch] = []
        self._latest_stf: int | None = None
        self._msgs: list = []
        self._cond = threading.Condition()
        self._init_reader()
        self._last_warn = 0.0
        self._warned_bad = 0

    def identify(self) -> str:
        """Open the link, ask the device for its DeviceID (GoToConfig, ReqDID) and put it back
        in measurement mode; no reader thread. Raises LinkLost (the port, or no answer)."""
        self.link.open()
        self.link.drain_input()
        try:
            self._request(go_to_config(), MID.GO_TO_CONFIG_ACK, "GoToConfig")
            m = self._request(req_did(), MID.DEVICE_ID, "ReqDID", required=False)
            device_id = ""
            if m is not None:
                try:
                    device_id = decode_device_id(m.data)
                except XsensError:
                    device_id = ""
            self._request(go_to_measurement(), MID.GO_TO_MEASUREMENT_ACK, "GoToMeasurement", required=False)
        finally:
            self.link.close()
        return f"Xsens MT, device ID {device_id}" if device_id else "Xsens MT (no device ID reported)"

    # ----------------------------------------------------------------------- reader thread
    def _on_link_lost(self) -> None:
        self._flush_stream()

    def _flush_stream(self) -> None:
        with self._cond:            # decode and store as one step (see _feed)
            batch = self.stream.flush()
            if len(batch):
                self._store(batch)

    def _feed(self, data: bytes) -> None:
        arrival = self.clock.now()
        # decoding counts the frames and storing makes them readable: one step under the lock
        # that ``counters`` and ``read`` take, so no snapshot of the counters ever includes
        # frames that ``read`` cannot yet return (a reader thread descheduled between the two
        # made a burst of ~800 counted frames missing from the reads that followed)
        with self._cond:
            batch = self.stream.feed(data)
            if batch.messages:
                self._msgs.extend(batch.messages)
            if len(batch):
                self._store(batch, arrival)
        c = self.stream.counters
        bad = c.bad_frames + c.truncated_frames + c.out_of_order
        if bad != self._warned_bad and time.monotonic() - self._last_warn > 1.0:
            self._last_warn, self._warned_bad = time.monotonic(), bad
            log.warning("%s: %d bad, %d truncated, %d out-of-order frames, %d dropped samples so far", self.name,
                        c.bad_frames, c.truncated_frames, c.out_of_order, c.dropped_samples)

    def _store(self, batch: MTData2Batch, arrival: float | None = None) -> None:
        stf = batch.sample_time_fine
        if self._stf0 is None and (stf >= 0).any():
            self._stf0 = int(stf[stf >= 0][0])
        if arrival is not None and stf.size and stf[-1] >= 0:
            self._track_offset(arrival, stf[stf >= 0] / SAMPLE_TIME_FINE_HZ)
        with self._cond:
            self._pending.append(batch)
            if stf.size and stf[-1] >= 0:
                self._latest_stf = int(stf[-1])
            self._chunks += 1
            self._cond.notify_all()

    def _await(self, mids: tuple[int, ...]):
        """Read until a message with one of ``mids`` (or an Error) arrives."""
        deadline = time.monotonic() + self.timeout_s
        while time.monotonic() < deadline and not self._stop.is_set():
            for i, m in enumerate(self._msgs):
                if m.mid in mids or m.mid == MID.ERROR:
                    del self._msgs[:i + 1]
                    return m
            self._msgs.clear()
            data = self.link.read_some(max(1e-3, min(0.05, deadline - time.monotonic())))
            if data:
                self._feed(data)
        return None

    def _request(self, msg: bytes, ack: int, what: str, tries: int = 3, required: bool = True):
        """Send ``msg`` until ``ack`` arrives (``tries`` times). An Error reply raises
        XsensConfigError, no reply LinkLost; unless not ``required``: then both return None
        (with a warning)."""
        for _ in range(tries):
            self._msgs.clear()
            self.link.write(msg)
            m = self._await((ack,))
            if m is None:
                continue
            if m.mid == MID.ERROR:
                code = m.data[0] if m.data else -1
                name = ErrorCode(code).name if code in ErrorCode._value2member_map_ else f"0x{code:02X}"
                if not required:
                    log.warning("%s: device answered %s with error %s", self.name, what, name)
                    return None
                raise XsensConfigError(f"{self.name}: device refused {what}: error {name}")
            return m
        if not required:
            log.warning("%s: no answer to %s from %s after %d tries", self.name, what, self.link.url, tries)
            return None
        raise LinkLost(self.name, f"no acknowledgement of {what} from {self.link.url}")

    def _check_identity(self) -> None:
        """ReqDID (config mode): keep the DeviceID on the first configuration; on a reconnect,
        raise XsensUnitChanged if the device now reports another one."""
        m = self._request(req_did(), MID.DEVICE_ID, "ReqDID", required=False)
        device_id = ""
        if m is not None:
            try:
                device_id = decode_device_id(m.data)
            except XsensError as exc:
                log.warning("%s: unreadable DeviceID: %s", self.name, exc)
        known = self.identity["device_id"]
        if self.configurations == 0:
            self.identity = {"device_id": device_id, "protocol": PROTOCOL}
            if not device_id:
                log.warning("%s: the device does not report its ID: the recording cannot name the unit "
                            "under test (set imu: serial: in the rig config)", self.name)
        elif known and device_id and device_id != known:
            raise XsensUnitChanged(
                f"{self.name}: a different unit is now on {self.link.url}: device ID {device_id}, but the "
                f"run started with {known}; its data are not recorded -- reconnect unit {known} and "
                "resume the run (rigctl resume), or start a new run for the other unit")
        elif known and not device_id:
            log.warning("%s: could not confirm the device ID after the reconnect (the run started with %s)",
                        self.name, known)

    def _configure(self) -> None:
        first = self.offset is None
        self.link.ensure()
        if first:       # bytes a previous user left in the port's buffer (e.g. a killed process)
            self.link.drain_input()
        self._request(go_to_config(), MID.GO_TO_CONFIG_ACK, "GoToConfig")
        if first:
            self._discard_preconfig()
        self._check_identity()
        ack = self._request(set_output_configuration(self.items), MID.SET_OUTPUT_CONFIGURATION_ACK,
                            f"the output configuration ({self.rate_hz} Hz)")
        if ack.data and decode_output_configuration(ack.data) != self.items:
            raise XsensConfigError(f"{self.name}: device applied a different output configuration: "
                                   f"{decode_output_configuration(ack.data)}")
        self._request(go_to_measurement(), MID.GO_TO_MEASUREMENT_ACK, "GoToMeasurement")
        self.configurations += 1
        self._finish_configure(f"no MTData2 frames from {self.link.url} after GoToMeasurement")

    def _discard_preconfig(self) -> None:
        """Forget frames decoded before our first configuration (the device was already
        streaming: stale buffered data or another configuration); they are not part of this run
        and their sample times lie before it."""
        with self._cond:
            self._pending.clear()
            self._latest_stf = None
        self._stf0 = None
        self.stream = MTData2Stream(wrap_ticks=self.stream.wrap_ticks)

    # ------------------------------------------------------------------------------- Imu
    def read(self) -> ImuBlock:
        if self._fatal is not None:
            raise self._fatal
        with self._cond:
            self._wait_aligned()
            batches = self._take_pending()
        if not batches:
            self._raise_if_down()
            return ImuBlock.empty()
        return self._to_block(batches)

    def _latest_run_time(self) -> float | None:
        return None if self._latest_stf is None else self._latest_stf / SAMPLE_TIME_FINE_HZ + self.offset

    def _to_block(self, batches: list[MTData2Batch]) -> ImuBlock:
        stf = np.concatenate([b.sample_time_fine for b in batches])
        acc = np.concatenate([b.acceleration for b in batches])
        gyr = np.concatenate([b.rate_of_turn for b in batches])
        temp = np.concatenate([b.temperature for b in batches])
        ok = (stf >= 0) & np.isfinite(acc).all(axis=1) & np.isfinite(gyr).all(axis=1) & np.isfinite(temp)
        if not ok.all():
            self.incomplete_frames += int((~ok).sum())
            stf, acc, gyr, temp = stf[ok], acc[ok], gyr[ok], temp[ok]
        counter = np.rint((stf - (self._stf0 or 0)) / self.ticks_per_sample).astype(np.int64)
        counter = np.maximum(counter, 0).astype(np.uint64)
        time_s = stf / SAMPLE_TIME_FINE_HZ + (self.offset or 0.0)
        keep = self._monotone(time_s)
        if not keep.all():
            time_s, counter, acc, gyr, temp = time_s[keep], counter[keep], acc[keep], gyr[keep], temp[keep]
        return ImuBlock(time=time_s, counter=counter, specific_force=acc, angular_rate=gyr, temperature=temp)

    # --------------------------------------------------------------------------- status
    @property
    def device_restarts(self) -> int:
        """Restarts of the MTi itself (a SampleTimeFine time base that began behind the last
        stamp, drivers/xsens_decode.py), as ``counters["device_restarts"]``: read on every
        engine poll (rigctl.devices.imu_restarts)."""
        return self.stream.counters.device_restarts

    @property
    def counters(self) -> dict:
        """Decoder and link diagnostics (totals since connect): one consistent snapshot, in which
        every frame counted as decoded is already returned by ``read`` or waiting for it."""
        with self._cond:
            d = asdict(self.stream.counters)
        d.update(incomplete_frames=self.incomplete_frames, offset_corrections=self.offset_corrections,
                 offset_unconfirmed=self.offset_unconfirmed, restamp_dropped=self.restamp_dropped, link_losses=self.link.losses,
                 reconnects=self.link.reconnects, configurations=self.configurations)
        return d


__all__ = ["XsensImu", "XsensConfigError", "XsensUnitChanged", "output_items"]
