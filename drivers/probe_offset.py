"""Controller time -> run time offset of a polled device (the turntable drivers), learnt from
request/reply probes and kept on their lower envelope for the whole run.

A probe sends a request at run time ``t0`` and gets a reply carrying the controller's sample time
``c`` at ``t1``. The sample was taken no later than the reply arrived, so with the true offset
``o`` (run time = c + o): ``o <= t1 - c``. Each probe thus gives an upper bound ``t1 - c``, above
``o`` by the sample's age at the reply's arrival (how stale the controller's sample was plus the
return path); a stale sample (the controller -- or an emulator's physics loop -- lagging) or a
slow reply only makes it larger. The offset is the lowest bound seen: over the 8 probes at
connect, then over every read (the lower envelope, as NTP-like filters keep the minimum-delay
sample). One stall at connect (the old offset, fixed by the connect probes, came out 14-29 s too
large at 100x when the emulator lagged then) is corrected by the first on-time read, and a
table time never leads the run clock at the reply.

Lowering the offset after connect is counted (``corrections``); a state that the lower offset
would stamp at or before the last one handed out is stamped just after it (``clamped``), so table
times keep increasing (the recording's table series is interpolated).
"""
from __future__ import annotations

import logging
import math

log = logging.getLogger(__name__)


class ProbeOffset:
    """See the module docstring. ``offset`` (s) is None before the first probe."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.offset: float | None = None
        self.best_rtt = math.inf
        self.corrections = 0
        self.clamped = 0
        self._connected = False
        self._last: float | None = None

    def probe(self, t0: float, t1: float, controller_s: float) -> None:
        """One request sent at run time ``t0``, answered at ``t1`` with controller time ``controller_s``."""
        if t1 < t0 or not math.isfinite(controller_s):
            return
        self.best_rtt = min(self.best_rtt, t1 - t0)
        est = t1 - controller_s
        if self.offset is None or est < self.offset:
            if self._connected and self.offset is not None:
                self.corrections += 1
                if self.offset - est > 0.1:
                    log.warning("%s: controller time offset lowered by %.6f s (the connect probes saw a "
                                "stale controller time)", self.name, self.offset - est)
            self.offset = est

    def connected(self) -> None:
        """The connect probes are over: later lowerings are counted as corrections."""
        self._connected = True

    def stamp(self, controller_s: float) -> float:
        """Run time of a controller time, never at or before the last one handed out."""
        t = controller_s + (self.offset or 0.0)
        if self._last is not None and t <= self._last:
            self.clamped += 1
            t = math.nextafter(self._last, math.inf)
        self._last = t
        return t
