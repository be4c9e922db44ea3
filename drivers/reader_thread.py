"""Devices read by a background thread.

:class:`ReconnectingReader`: a device on a link read by a background thread that configures it,
pumps its bytes and, when the link drops, reconnects with the link's backoff and configures it
again.

Subclasses set :attr:`ReconnectingReader.config_error` (the exception their ``_configure`` raises
when the device refuses a command: fatal, reported by ``read``; so is a
:class:`rigctl.devices.DeviceFault` such as another unit on the port) and implement ``_configure``
(open the link if needed, configure, then ``self._configured.set()``) and ``_pump`` (read once,
decode, store). ``_on_link_lost`` runs in the thread when the link is lost (e.g. flush a decoder).
Any other exception in the thread is fatal too: it is logged and re-raised by the subclass's
``read`` through :attr:`_fatal`.

:class:`HostTimedPulses`: edges a background thread time-stamps on a host clock (GPIO lines,
modem-status lines), mapped onto the run clock and handed out by ``read``.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import numpy as np

from rigctl.devices import Clock, DeviceFault, LinkLost, Pulses

from .serial_link import SerialLink

log = logging.getLogger(__name__)


class ReconnectingReader:
    """Reader-thread life cycle shared by the streaming drivers (Xsens IMU, NovAtel marks)."""

    config_error: type[BaseException] = RuntimeError
    name: str
    link: SerialLink

    def _init_reader(self) -> None:
        self._stop = threading.Event()
        self._configured = threading.Event()
        self._fatal: BaseException | None = None
        self._down_since: float | None = None  # time.monotonic() when the link was lost
        self._streamed = False                 # configured at least once (outages count from then)
        self._thread: threading.Thread | None = None

    def _start_reader(self, wait_s: float, what: str) -> None:
        """Start the thread and wait up to ``wait_s`` (wall) for the first configuration; on
        failure close and raise the thread's error, else LinkLost(``what``)."""
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-reader", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + wait_s
        while not self._configured.wait(0.01):
            if self._fatal is not None or time.monotonic() > deadline:
                err = self._fatal or LinkLost(self.name, what)
                self.close()
                raise err

    def _configure(self) -> None:  # pragma: no cover - subclass duty
        raise NotImplementedError

    def _pump(self) -> None:  # pragma: no cover - subclass duty
        raise NotImplementedError

    def _on_link_lost(self) -> None:
        pass

    def _outage_began(self) -> None:
        """In the thread, once per outage, after :meth:`_on_link_lost`: the link of a configured
        device was lost (a reader that hands out data marks where, see StreamReader)."""

    def _outage_ended(self, down_since: float, up_at: float) -> None:
        """In the thread: the device is configured again after an outage from ``down_since`` to
        ``up_at`` (time.monotonic(), s)."""

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                if not self._configured.is_set():
                    self._configure()
                    if self._down_since is not None and self._streamed:
                        self._outage_ended(self._down_since, time.monotonic())
                    self._down_since, self._streamed = None, True
                self._pump()
            except LinkLost:
                self._configured.clear()
                new_outage = self._down_since is None and self._streamed
                if self._down_since is None:
                    self._down_since = time.monotonic()
                self._on_link_lost()
                if new_outage:
                    self._outage_began()
                self._stop.wait(max(0.01, self.link.backoff.wait_s()))
            except (self.config_error, DeviceFault) as exc:  # e.g. another unit on the port
                self._fatal = exc
                return
            except Exception as exc:  # noqa: BLE001 - reported through read()
                log.exception("%s: reader thread failed", self.name)
                self._fatal = exc
                return

    def link_down_s(self) -> float | None:
        """Wall seconds since the link was lost, or None while it is up."""
        return None if self._down_since is None else time.monotonic() - self._down_since

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5)
        self.link.close()


class HostTimedPulses:
    """Pulse edges time-stamped by a thread on a host clock (GPIO and modem-status lines).

    The thread stores run times with :meth:`_add`; :meth:`read` hands them out as
    :class:`rigctl.devices.Pulses` (no GPS time) and raises the thread's error, if it failed.
    Host time maps onto the run clock by the offset taken when the thread starts, scaled by the
    run clock's speed. Subclasses set ``source`` and ``reader_what`` (for messages).
    """

    source: str
    reader_what: str
    name: str
    clock: Clock

    def _init_pulses(self) -> None:
        self._times: list[float] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._fatal: BaseException | None = None

    def _start_pulses(self, target: Callable[[], None], host_ns: int, suffix: str) -> None:
        """Take the host-to-run offset (``host_ns``: the host clock now) and start ``target``."""
        self._host0, self._run0 = host_ns, self.clock.now()
        self.speed = float(getattr(self.clock, "speed", 1.0))
        self._thread = threading.Thread(target=target, name=f"{self.name}-{suffix}", daemon=True)
        self._thread.start()

    def to_run_time(self, host_ns: int) -> float:
        """Run time, s, of a host timestamp, ns (see the class docstring)."""
        return self._run0 + (host_ns - self._host0) * 1e-9 * self.speed

    def _add(self, times: list[float]) -> None:
        with self._lock:
            self._times.extend(times)

    def read(self) -> Pulses:
        if self._fatal is not None:
            raise RuntimeError(f"{self.name}: {self.reader_what} failed: {self._fatal}")
        with self._lock:
            t, self._times = self._times, []
        n = len(t)
        return Pulses(time=np.asarray(t, float), gps_week=np.full(n, -1, np.int32), gps_seconds=np.full(n, np.nan),
                      source=self.source)

    def _stop_thread(self, timeout_s: float) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)
