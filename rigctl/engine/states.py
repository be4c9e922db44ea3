"""The run state machine: idle, running, pausing, paused, aborting, faulted.

Only the transitions in :data:`TRANSITIONS` are legal; anything else raises
:class:`IllegalTransition` (a programming error, never a user error). Every transition is
passed to the listeners, which log it (run log, daemon log) and write it to the run's
recording as an event of kind ``state`` with the message ``"<old> -> <new>: <reason>"``.

::

    idle --start--> running --suspend/pause--> pausing --table stopped--> paused
      ^               |  ^                                                 |  |
      |               |  +---------------------- resume (clear + hold) ----+  |
      +--- done ------+                                                       |
      +--- done ---- aborting <--- abort / SIGINT / SIGTERM (from running, pausing, paused)
      +--- reset --- faulted  <--- unhandled error (from any state but idle)
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable

STATES = ("idle", "running", "pausing", "paused", "aborting", "faulted")

TRANSITIONS: dict[str, tuple[str, ...]] = {
    "idle": ("running",),
    "running": ("pausing", "aborting", "faulted", "idle"),
    "pausing": ("paused", "aborting", "faulted"),
    "paused": ("running", "aborting", "faulted"),
    "aborting": ("idle", "faulted"),
    "faulted": ("idle",),
}

Listener = Callable[[str, str, str], None]


class IllegalTransition(RuntimeError):
    """A transition not in :data:`TRANSITIONS` was attempted."""


class StateMachine:
    """Thread-safe current state with legal transitions and listeners ``(old, new, reason)``."""

    def __init__(self, initial: str = "idle") -> None:
        if initial not in STATES:
            raise ValueError(f"unknown state {initial!r}")
        self._state = initial
        self._reason = ""
        self._since = time.time()
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self.listeners: list[Listener] = []

    @property
    def state(self) -> str:
        return self._state

    @property
    def reason(self) -> str:
        """Why the machine entered its current state."""
        return self._reason

    @property
    def since(self) -> float:
        """Unix time of the last transition, s."""
        return self._since

    def can(self, new: str) -> bool:
        return new in TRANSITIONS[self._state]

    def to(self, new: str, reason: str = "") -> None:
        """Move to ``new``; a no-op if already there; IllegalTransition if not allowed."""
        with self._lock:
            old = self._state
            if new == old:
                return
            if new not in STATES:
                raise ValueError(f"unknown state {new!r}")
            if new not in TRANSITIONS[old]:
                raise IllegalTransition(f"{old} -> {new} is not a legal transition ({reason})")
            self._state, self._reason, self._since = new, reason, time.time()
            self._changed.notify_all()
            listeners = list(self.listeners)
        for fn in listeners:
            fn(old, new, reason)

    def wait_for(self, states: tuple[str, ...], timeout: float | None = None) -> bool:
        """Block until the state is one of ``states``; False on timeout."""
        with self._changed:
            return self._changed.wait_for(lambda: self._state in states, timeout)
