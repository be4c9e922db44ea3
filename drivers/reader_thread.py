"""A device on a link read by a background thread that configures it, pumps its bytes and, when
the link drops, reconnects with the link's backoff and configures it again.

Subclasses set :attr:`ReconnectingReader.config_error` (the exception their ``_configure`` raises
when the device refuses a command: fatal, reported by ``read``) and implement ``_configure``
(open the link if needed, configure, then ``self._configured.set()``) and ``_pump`` (read once,
decode, store). ``_on_link_lost`` runs in the thread when the link is lost (e.g. flush a decoder).
Any other exception in the thread is fatal too: it is logged and re-raised by the subclass's
``read`` through :attr:`_fatal`.
"""
from __future__ import annotations

import logging
import threading
import time

from rigctl.devices import LinkLost

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

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                if not self._configured.is_set():
                    self._configure()
                    self._down_since = None
                self._pump()
            except LinkLost:
                self._configured.clear()
                if self._down_since is None:
                    self._down_since = time.monotonic()
                self._on_link_lost()
                self._stop.wait(max(0.01, self.link.backoff.wait_s()))
            except self.config_error as exc:
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
