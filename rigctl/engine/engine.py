"""The engine: executes a compiled plan of steps against a rig, recording everything.

The engine owns no hardware: it is handed devices that follow the small protocols of
:mod:`rigctl.devices` and a clock. For every step it commands the table, waits until the table
has *settled* (the controller reports in position / at rate AND every axis stayed inside the
step's position and rate windows for the hold time), discards the transient, samples for the
step's window, and writes a segment record. It never samples before the hold criteria are met;
a settle timeout stops the run with a message naming the step and what was out of window.

Unattended operation: every poll is handed to the :mod:`rigctl.config.suspenders`. When one trips
(IMU link lost or data gap, table fault or interlock open, temperature out of band, disk space
low, operator pause) the engine goes ``running -> pausing -> paused`` (:mod:`rigctl.engine.states`),
stops the table, writes the step in flight as an ``incomplete`` segment (with its sample range),
keeps polling until every suspender has been clear for the hold time, then goes back to
``running`` and re-runs the interrupted step from its start: segments are all-or-nothing. One
that trips after a sampling window, while its last samples are awaited, lets the samples decide:
a window they cover is a complete step and the pause comes before the next one (:meth:`execute`).
Memory stays flat over any step length: a sample window keeps running sums, not per-poll lists.
"""
from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .. import errors
from ..clock import VirtualClock, suggested_speed
from ..devices import (AxisStatus, Clock, DeviceFault, Imu, LinkLost, PulseSource, TableState, Turntable,
                       imu_reconnecting, imu_restarts)
from .procedure import CHAMBER_KINDS, Step
from ..progress import CounterGaps, NullProgress, Progress
from ..recording.recorder import Elide, Recorder, Segment, event_text
from .states import StateMachine
from ..config.suspenders import Observation, SuspenderSet


#: Times closer than this are equal (sums of poll intervals carry rounding), s.
TIME_EPS = 1e-6

#: After a sampling window, the engine waits for the samples still in flight (a serial link, a
#: decoder batch) up to 2 s of rig time -- and, on a clock faster than the wall (an emulated rig
#: at 100x), at least this much wall time: the delay is the host's, in wall time, and 2 s of rig
#: time at 100x is 20 ms, less than one scheduling delay of a loaded host (at load 10-12 on 2
#: cores, 17 of 47 wired 24-position runs at 100x cut a 5 s window short, 3 to no sample at all,
#: with every sample of it recorded after the wait). 1.5 s since 0.5 s was not enough at load
#: 18-23 (a 5 s window of a wired 24-position run at 100x got 96 of its 500 samples). The wait
#: ends as soon as a sample at or after the window's end has arrived: it costs time only when
#: samples are really missing.
WINDOW_WAIT_WALL_S = 1.5

#: A sampling window whose samples cover less than the window asked for (their own time span,
#: first to last sample plus one sample period) by more than this many sample periods is short:
#: one period because the window's edges fall between samples, one for the jitter of the
#: samples' time stamps (a link's latency that varies from sample to sample). A short window is
#: never recorded as a segment: the step is sampled again through the suspension path
#: (:meth:`Engine.suspend`), at most :data:`SHORT_WINDOW_TRIES` times in all before the run stops.
SHORT_WINDOW_TOL_PERIODS = 2.0

#: sampling attempts of one step whose window came out short before the run stops (resumable)
SHORT_WINDOW_TRIES = 3


#: A scaled clock that an in-process emulator had to set back is measured over this much wall
#: time before the run says it cannot keep up (Engine._watch_pace), s.
PACE_WINDOW_WALL_S = 2.0


def pace_message(speed: float, achieved: float) -> str:
    """The one line saying the host cannot keep up with ``speed``, and what to do."""
    suggest = suggested_speed(achieved)
    got = f"{achieved:.0f}" if achieved >= 10 else f"{achieved:.2g}"
    return (f"the host cannot keep up with clock speed {speed:g}x: the emulator computes about "
            f"{got}x here, so rig time runs at that speed and the run takes about "
            f"{speed / max(achieved, 1e-9):.1f} times the wall time planned; set 'speed: {suggest:g}' "
            "in the rig config, or 'clock: virtual' to run as fast as the host computes")


#: Devices whose time runs at less than this fraction of the run's clock speed keep time too
#: slowly (Engine._watch_pace, slow_rig_speed)
PACE_SLOW_FRACTION = 0.9


#: Table reads in a row that find its time unchanged before a slow rig is said to have a frozen
#: table clock (:func:`slow_rig_message`): an emulator's physics waiting for an IMU stream its
#: client does not take (sim/links.py FlowPtyEndpoint) stands the table's time still.
STILL_TABLE_READS = 20


def slow_rig_message(speed: float, achieved: float, still: tuple[int, float] | None = None) -> str:
    """The one line saying a rig on the wire keeps time slower than the run's clock asks.

    A run at ``speed`` x real time (``clock: scaled``) talks to an emulator (``rigctl sim up
    --speed``); its devices' time -- table controller time, IMU sample times -- advancing at
    ``achieved`` x real time < ``speed`` (end to end: the slower of the two) means the emulator
    cannot run the rig that fast on this machine (a real device's clock does not lag the host's
    by percents). Its samples then fall further behind the clock every second: an IMU stream that
    starts only when the physics reaches the clock ('no stream'), windows that come out short.

    ``still``: (table reads, IMU stream lag s of rig time) when the IMU stream, not the table,
    fell behind: it lagged the run's clock by that much -- the emulator's physics waiting for an
    IMU stream this host does not read as fast as it comes -- said as the cause, with the table
    reads that found its time standing still meanwhile (0: it crept on). The speed advised is :func:`rigctl.clock.suggested_speed` of ``achieved``, never below
    1; when even that is more than the rig kept, the host is too slow for real time."""
    got = f"{achieved:.0f}" if achieved >= 10 else f"{achieved:.2g}"
    cause = "cannot compute the rig that fast"
    if still is not None:
        frozen = f"the table's clock did not advance in {still[0]} reads while " if still[0] else ""
        cause = (f"cannot run the rig that fast: {frozen}the IMU stream lagged {still[1]:.0f} s behind the "
                 f"clock (the emulator waits for an IMU stream this host does not read as fast as it comes)")
    head = (f"the rig's devices keep time at about {got}x real time, slower than the {speed:g}x "
            f"of the run's clock: the emulator ('rigctl sim up --speed {speed:g}') {cause} on this machine, "
            f"so its devices fall ever further behind the clock; ")
    suggest = suggested_speed(achieved)
    if suggest < 1.0:
        return head + ("this host is too slow to run the emulated rig even at real time (--speed 1): "
                       "run it on a faster or less loaded machine")
    return head + f"restart it with --speed {suggest:g} or less and run with the wired config it writes"


def slow_rig_speed(speed: float, wall_s: float, device_s: float) -> float | None:
    """The speed the rig's devices keep time at (``device_s`` of their time in ``wall_s`` of wall
    time), when a clock at ``speed`` x real time (> 1: an emulated rig) runs faster than that by
    more than :data:`PACE_SLOW_FRACTION`; else None."""
    if speed <= 1.0 or wall_s <= 0.0:
        return None
    achieved = device_s / wall_s
    return achieved if achieved < PACE_SLOW_FRACTION * speed else None


def rewarm_due(event_time: np.ndarray, event_kind: np.ndarray, event_message: np.ndarray,
               seg_kind: np.ndarray, seg_status: np.ndarray, seg_t_start: np.ndarray) -> str | None:
    """Whether a recording cut off after a ``device-restart`` event still owes the IMU its warm-up
    (for ``rigctl resume``, :attr:`Engine.rewarm`): the latest such event's message when no
    complete ``warmup`` segment started at or after it, else None. Times on the file's time
    base, s; kinds and statuses as the recording's bytes."""
    restarts = np.flatnonzero(np.asarray(event_kind) == b"device-restart")
    if not restarts.size:
        return None
    i = restarts[np.argmax(np.asarray(event_time, float)[restarts])]
    t = float(event_time[i])
    warm = (np.asarray(seg_kind) == b"warmup") & (np.asarray(seg_status) == b"complete")
    if np.any(np.asarray(seg_t_start, float)[warm] >= t):
        return None
    msg = event_message[i]
    return msg.decode("utf-8", "replace") if isinstance(msg, bytes) else str(msg)


class RunError(errors.RunFailure):
    """A failure at run time (settle timeout, device fault)."""


class Interrupted(errors.Interrupted):
    """The run was interrupted (SIGINT / SIGTERM / abort)."""


class Suspend(Exception):
    """One or more suspenders tripped: ``reasons`` maps suspender name -> readable reason."""

    def __init__(self, reasons: dict[str, str]) -> None:
        self.reasons = dict(reasons)
        #: the step's segment, recorded complete, when the suspension tripped after its window
        #: while its last samples were awaited and they cover it (Engine.execute): the pause
        #: then comes between this step and the next, nothing is cut off
        self.segment: Segment | None = None
        super().__init__("; ".join(reasons.values()))

    def merge(self, other: "Suspend") -> None:
        """Add the suspenders of ``other`` not already named (a trip seen later in the same wait:
        :meth:`Engine._window_rows`); the message names them all."""
        for name, reason in other.reasons.items():
            self.reasons.setdefault(name, reason)
        self.args = ("; ".join(self.reasons.values()),)


#: a suspender that trips again in one pause (after a poll that found it clear) gets a suspend
#: event each time -- a second data gap names its own counters, a second link loss its time --
#: up to this many times per pause; further trips of it are counted in one 'info' event at the
#: resume (a condition flapping at its threshold through a long pause)
PAUSE_RETRIP_EVENTS = 20


@dataclass
class PauseTrips:
    """The suspenders of one pause, for its events: ``names``, every one that tripped in it (its
    resume names them); ``active``, those tripped at its latest poll; ``again``, per name, the
    trips after its first (a trip is a poll that finds it tripped after one that found it clear)."""

    names: set[str]
    active: set[str]
    again: dict[str, int]

    @classmethod
    def begin(cls, reasons: dict[str, str]) -> "PauseTrips":
        return cls(set(reasons), set(reasons), {})


@dataclass
class Rig:
    """The devices a run talks to, and the clock of their time base."""

    table: Turntable
    imu: Imu
    pulses: PulseSource
    clock: Clock
    description: str = ""
    #: optional operator stand-in (emulator): ``prompt(step, t_start, duration)`` is called when
    #: a step with a prompt starts sampling (e.g. the emulated operator taps the IMU)
    operator: Any = None
    #: the climatic chamber (rigctl.config.chamber.Chamber), None on a rig without one
    chamber: Any = None
    #: the chamber's band for the 'chamber' suspender (min, max) degC
    chamber_band: tuple[float, float] = (-70.0, 180.0)


#: a table whose time stands still for this many settle timeouts of the run's clock, and at
#: least Engine.still_wall_s of wall time, fails the step (Engine.settle measures its hold and
#: timeout on the table's time). The wall-time floor: on a clock faster than the wall an emulated
#: table stands still while its host holds the physics back (7.5 s of wall time, 753 s of rig
#: time at 100x, at load 16-18 on 2 cores: a wired 24-position run failed on it)
SETTLE_STILL_TIMEOUTS = 10
SETTLE_STILL_WALL_S = 60.0


#: the status bits settle_check tests, as plain ints (IntFlag operations cost microseconds, at every poll)
_FAULT, _AT_RATE, _TARGET_REACHED = int(AxisStatus.FAULT), int(AxisStatus.AT_RATE), int(AxisStatus.TARGET_REACHED)


def angle_error(measured: np.ndarray, commanded: np.ndarray) -> np.ndarray:
    """measured - commanded wrapped to (-pi, pi], rad."""
    d = np.asarray(measured) - np.asarray(commanded)
    return np.pi - np.mod(np.pi - d, 2 * np.pi)


def settle_check(state: TableState, step: Step) -> str | None:
    """None when the table is inside the step's windows and reports settled, else the reason."""
    pol = step.settle
    rate_axes = ~np.isnan(step.rates)
    want_rate = np.where(rate_axes, step.rates, 0.0)
    for i in range(3):
        status = int(state.status[i])
        if status & _FAULT:
            return f"axis {i + 1} reports a fault (status 0x{status:04x})"
        flag = _AT_RATE if rate_axes[i] else _TARGET_REACHED
        if not status & flag:
            return f"axis {i + 1} not yet {'at rate' if rate_axes[i] else 'in position'}"
    pos_err = angle_error(state.angle, step.angles)
    for i in np.flatnonzero(~rate_axes):
        if abs(pos_err[i]) > pol.position_window:
            return (f"axis {i + 1} position error {math.degrees(pos_err[i]):+.4f} deg outside "
                    f"+-{math.degrees(pol.position_window):g} deg")
    rate_err = state.rate - want_rate
    for i in range(3):
        if abs(rate_err[i]) > pol.rate_window:
            return (f"axis {i + 1} rate error {math.degrees(rate_err[i]):+.4f} deg/s outside "
                    f"+-{math.degrees(pol.rate_window):g} deg/s")
    return None


class Engine:
    """Runs steps on a rig into a recorder."""

    def __init__(self, rig: Rig, recorder: Recorder, *, settle_poll_s: float = 0.05,
                 sample_poll_s: float = 0.5, log: Callable[..., None] | None = None,
                 suspenders: SuspenderSet | None = None, states: StateMachine | None = None,
                 pause_poll_s: float = 0.25, max_pause_s: float | None = None,
                 open_interlocks: bool = False, progress: Progress | None = None,
                 imu_rate_hz: float = 0.0) -> None:
        self.rig, self.rec = rig, recorder
        #: the IMU's output rate (the rig config's), Hz; 0: taken from the window's own samples
        self.imu_rate_hz = float(imu_rate_hz)
        #: step index -> sampling attempts whose window came out short (see :meth:`_check_window`)
        self.short_windows: dict[int, int] = {}
        self.progress = progress if progress is not None else NullProgress()
        self.gaps = CounterGaps()  # dropped IMU samples (counter gaps) for the progress display
        self.settle_poll_s, self.sample_poll_s = settle_poll_s, sample_poll_s
        self.pause_poll_s, self.max_pause_s = pause_poll_s, max_pause_s
        self.open_interlocks = open_interlocks
        self.log = log or (lambda kind, msg, **kw: None)
        self.suspenders = suspenders if suspenders is not None else SuspenderSet()
        if not isinstance(rig.clock, VirtualClock):     # the no-sample wait's wall-time floor
            self.suspenders.clock_speed = float(getattr(rig.clock, "speed", 1.0))
        self.states = states if states is not None else StateMachine()
        self.abort_requested: str | None = None
        self._track: deque | None = None
        self._win_start: float | None = None
        self._first_row: int | None = None
        self._first_time: float | None = None  # IMU time of the window's first sample, s
        #: a suspension that tripped while a window's last samples were awaited (_window_rows), and
        #: the time its samples covered when they did not cover the window, s
        self._tail_sus: Suspend | None = None
        self._tail_covered: float | None = None
        self.last_state: TableState | None = None
        self.current_step: Step | None = None
        self.sampling_from: int | None = None  # first IMU row of the window being sampled
        self.n_suspensions = 0
        self._flushed_once = False
        #: the chamber is read at most this often (rig time), s; its last reading and trip reason
        self.chamber_poll_s = 1.0
        self.last_chamber: Any = None
        self._chamber_t = -math.inf
        #: ... and at most this often in wall time (a chamber on a slow link, a fast clock), s
        self.chamber_poll_wall_s = 0.1
        self._chamber_wall = -math.inf
        self._chamber_reason: str | None = None
        #: (time, min, max) of the IMU temperature per poll, while a chamber-wait step runs
        self._temps: deque | None = None
        self.live: Any = None  # a rigctl.service.livefeed.LiveFeed (the daemon's live views), or None
        self.deferred_pause: str | None = None  # an operator pause due at the end of the step in flight
        #: warm-up step index -> seconds of warm-up already done in earlier attempts of that step
        #: with the IMU powered all along (see :meth:`suspend`)
        self.warmup_done: dict[int, float] = {}
        #: why the IMU must be warmed up again before the next measurement: it restarted (lost
        #: power: its device time began again, :func:`rigctl.devices.imu_restarts`) and no whole
        #: warm-up ran since (the ``device-restart`` event; a resumed run sets it from the
        #: recording, :func:`rewarm_due`); None when it is warm
        self.rewarm: str | None = None
        self._restarts: int | None = None      # the IMU's restart count at the last poll
        self._warmup: Step | None = None       # the procedure's warm-up step (run)
        self._last_done: Step | None = None    # the last step recorded complete
        self._motion: list[Step] | None = None  # the steps run() executes (run)
        self._rewarm_before: Step | None = None  # the step a re-warm in flight precedes (_rewarm)
        self._sampled = False                  # the step in flight began its window (this attempt)
        #: whether a window's last samples are awaited (_window_rows); the rig time of a restart
        #: noticed meanwhile, s, said once those samples decide (_tail_restart_said)
        self._awaiting_tail = False
        self._tail_restart: float | None = None
        #: wall time over which the speed rig time really runs at is measured (_watch_pace), s;
        #: whether the run said it cannot keep up
        self.pace_window_s = PACE_WINDOW_WALL_S
        self.pace_warned = False
        self._pace: tuple[float, float, float, float] | None = None  # (wall, table t, slipped, IMU t)
        #: (wall, IMU stream time s) at the first IMU sample the pace watch saw: the rig's speed
        #: end to end since (the stream's own time), when a window's table time stood still
        self._pace_origin: tuple[float, float] | None = None
        self._imu_t = math.nan                  # the latest IMU sample's time, s
        self._still_reads = 0                   # table reads in a row that found its time unchanged
        self._stream_slower = False             # the IMU stream kept time slower in the last pace window
        #: the IMU link was lost or reconnecting in the pace window in progress: its stream's time
        #: then measures the outage, not the rig's pace (the table's alone does)
        self._imu_down = False
        self._pace_slow: float | None = None  # the devices' speed in the last pace window, if slow
        #: the line saying the rig's devices keep time slower than the clock (slow_rig_message), once seen
        self.slow_rig: str | None = None
        #: wall time a table's time must stand still for, at least, to fail a settle, s
        self.still_wall_s = SETTLE_STILL_WALL_S

    def request_abort(self, reason: str = "interrupted") -> None:
        """Ask the run to stop at the next poll (safe to call from a signal handler)."""
        self.abort_requested = reason

    def request_pause(self, reason: str = "paused by operator", deferred: bool = False) -> None:
        """Pause at the next poll (thread-safe); the step in flight re-runs after resume. With
        ``deferred`` the pause waits for the end of the step in flight (nothing re-runs)."""
        if deferred:
            self.deferred_pause = reason
        else:
            self.suspenders.operator = reason

    def request_resume(self) -> None:
        """Lift an operator pause; the run resumes once every suspender has been clear for the
        hold time."""
        self.suspenders.operator = None

    # -- polling -------------------------------------------------------------------------------
    def poll(self, check: bool = True, safe_state: bool = False) -> TableState:
        """Read every device once, record what came in and evaluate the suspenders; raise
        Interrupted on an abort request and (if ``check``) Suspend when a suspender trips.
        ``safe_state``: an IMU fault is noted, not raised (the table must still be read)."""
        clock = self.rig.clock
        obs = Observation(t=clock.now(), imu_reconnecting=imu_reconnecting(self.rig.imu))  # before the read
        try:
            block = self.rig.imu.read()
            obs.imu = block
            if self._track is not None and len(block):
                self._track_block(self.rec.n_imu, block.time)
            self.rec.append_imu(block)
            self.gaps.add(block.counter)
            if len(block):
                self._imu_t = float(block.time[-1])
            if self.live is not None:
                self.live.add_imu(block)
        except LinkLost as exc:
            obs.imu_error = str(exc)
        except DeviceFault as exc:  # e.g. another unit on the IMU port: fatal, except while
            if not safe_state:      # going to the safe state, which must still read the table
                raise
            obs.imu_error = str(exc)
        self._imu_down |= bool(obs.imu_error or obs.imu_reconnecting)
        restarted = self._watch_restarts(obs.t, closing=safe_state)
        try:
            self.rec.append_pulses(self.rig.pulses.read())
        except LinkLost as exc:
            self.log("warning", f"pulse source: {exc}")
        if self.rig.chamber is not None:
            self._poll_chamber(obs.t)
            obs.chamber_reason = self._chamber_reason
        if self._temps is not None and obs.imu is not None and len(obs.imu):
            temp = obs.imu.temperature
            self._temps.append((obs.t, float(np.min(temp)), float(np.max(temp))))
        try:
            state = self.rig.table.read()
            obs.table = state
            same = self.last_state is not None and float(state.time) == float(self.last_state.time)
            self._still_reads = self._still_reads + 1 if same else 0
            self.rec.append_table(state)
            self.last_state = state
            if self.live is not None:
                self.live.add_table(state)
        except LinkLost as exc:
            obs.table_error = f"table link lost: {exc}"
            state = self.last_state
        if not self._flushed_once:  # what the devices sent while connecting: on disk at once
            self._flushed_once = True
            self.rec.flush()
        self.progress.update(obs.t, state, self.rec.n_imu, self.gaps.dropped)
        self._watch_pace(state.time if state is not None else obs.t)
        if self.abort_requested and not safe_state:  # a second signal: the safe state goes on
            raise Interrupted(self.abort_requested)
        tripped = self.suspenders.check(obs)
        if self.rec.holding:
            tripped["disk"] = tripped.get("disk") or self.rec.holding
            self.suspenders.active, self.suspenders.clear_since = tripped, None
        if restarted is not None:   # an event, not a state: it trips this poll only
            tripped = {**tripped, "imu-restart": restarted}
        if tripped and check:
            raise Suspend(tripped)
        if state is None:
            if check:
                raise Suspend({"table": "table link lost before its first reading"})
            nan3 = np.full(3, np.nan)
            return TableState(time=obs.t, angle=nan3, rate=nan3, status=(0, 0, 0))
        return state

    def _watch_restarts(self, t: float, closing: bool = False) -> str | None:
        """The reason to pause when the IMU restarted since the last poll (its driver's restart
        count rose, :func:`rigctl.devices.imu_restarts`), else None.

        A restart is a power loss of the unit, not a link drop (after which its device time
        continues): a new turn-on bias, and the unit is thermally cold. It is recorded as a
        ``device-restart`` event naming where it was noticed and the last complete step (the
        calibration reports the positions on each side, rigctl.analysis.calibration), said in
        one run-log line, and sets :attr:`rewarm` when a step still runs: the procedure's
        warm-up runs again before it (:meth:`run`). All through :meth:`_restart_said`:

        * in a step, before or in its window: the step is cut off and runs (is sampled) again;
        * while the window's last samples are awaited (:meth:`_window_rows`): said once they
          decide (:meth:`_tail_restart_said`) -- they cover it: the step is complete and the
          restart lies before the next step, or after the last window (no step runs after it,
          no re-warm); they stop inside it: as in the step;
        * between steps: before the step after the last complete one;
        * ``closing``: noticed in the end-of-run safe state (:meth:`safe_state`): no step runs
          after it, no re-warm is planned or promised (a resumed run still warms up first:
          :func:`rewarm_due` reads the event)."""
        n = imu_restarts(self.rig.imu)
        if self._restarts is None or n <= self._restarts:
            self._restarts = n          # the first poll, or a driver whose counters began again
            return None
        self._restarts = n
        self.warmup_done.clear()    # warm-up time kept from before the restart counts no more
        step = self.current_step
        if closing:
            self._restart_said(t, ("in the end-of-run safe state",), None, None)
            return None
        if self._awaiting_tail:     # after the window: its samples decide what it means (execute)
            self._tail_restart = t
        elif step is not None:
            self._restart_said(t, (f"in step {step.index + 1} (", Elide(step.label), ")" + (
                "" if self._sampled else " before its window")), step, "is sampled again" if self._sampled else "runs")
        else:
            then = self._step_after(self._last_done)
            self._restart_said(t, ("between steps",), then, "runs")
        at = (f"after step {step.index + 1}'s window" if self._awaiting_tail else
              f"in step {step.index + 1} ({step.label})" if step is not None else "between steps")
        return f"IMU restarted {at} (device time began again)"

    def _step_after(self, step: Step | None) -> Step | None:
        """The step run() executes after ``step`` (None: the first) completes, or None when no
        step follows it: the re-warm's is the step it precedes (:meth:`_rewarm`)."""
        if step is not None and self._rewarm_before is not None and step.kind == "warmup":
            return self._rewarm_before
        motion = self._motion or []
        if step is None:
            return motion[0] if motion else None
        return next((s for s in motion if s.index > step.index), None)

    def _tail_restart_said(self, step: Step, complete: bool, stopping: bool = False) -> None:
        """Say the restart noticed while ``step``'s last samples were awaited (if any), now that
        they decided: ``complete`` -- the step is done and the restart lies before the step that
        follows it (or after the last); else the step is sampled again. ``stopping``: the wait
        was cut by what ends the run (an abort, a device fault) before they decided: the step is
        not recorded complete, and only a resumed run runs it again (:meth:`_restart_said`)."""
        t, self._tail_restart = self._tail_restart, None
        if t is None:
            return
        if not complete:
            self._restart_said(t, (f"in step {step.index + 1} (", Elide(step.label), ")"),
                               step, "is sampled again", stopping=stopping)
            return
        then = self._step_after(step)
        self._restart_said(t, (f"after step {step.index + 1}'s window, " +
                               (f"before step {then.index + 1}" if then is not None else "the last"),),
                           then, "runs", done=step)

    def _restart_said(self, t: float, where: tuple[str, ...], then: Step | None, how: str | None,
                      done: Step | None = None, stopping: bool = False) -> None:
        """The one decision for a restart of the IMU noticed at rig time ``t``, s, ``where`` (in a
        step, after its window, between steps, in the end-of-run safe state): the
        ``device-restart`` event and its one run-log line say what the engine then does, and
        :attr:`rewarm` is set to do it. ``then``: the step that runs next (``how``: 'runs' or 'is
        sampled again' -- the step the restart cut off); None: no step runs after it (the last
        window is done), so no warm-up is promised or planned (a resumed run still warms up
        first: :func:`rewarm_due` reads the event). ``done``: the last complete step, when the
        engine has not recorded it yet (:attr:`_last_done` otherwise).

        The re-warm runs before the first step from ``then`` on that is not a chamber step
        (:meth:`run`: chamber steps run without it); the chamber steps before that one are said
        first, and when only chamber steps are left no warm-up is planned. ``stopping``: the run
        ends here (an abort, a device fault): no step runs in this session, and a resumed run
        (``rigctl resume``, :func:`rewarm_due`) warms up first, then runs ``then`` again (the
        run log adds that the window's last samples were awaited).

        ``where``: the parts of the place (step labels as :class:`Elide`); the event
        (:func:`rigctl.recording.recorder.event_text`, 200 bytes) shortens the labels, never what
        the engine then does."""
        done, warm = done or self._last_done, self._warmup
        last = ((f"last complete step {done.index + 1} (", Elide(done.label), ")") if done is not None
                else ("no step complete yet",))
        said = "".join(where) + (" while its window's last samples were awaited" if stopping else "")
        ahead = [s for s in self._motion or [] if then is not None and s.index >= then.index] or \
            ([then] if then is not None else [])       # the steps run() executes from ``then`` on
        measured = next((s for s in ahead if s.kind not in CHAMBER_KINDS), None)  # the re-warm's
        chambers = [s for s in ahead if measured is None or s.index < measured.index]
        if then is None:
            plan = what = "no step runs after it"
        elif stopping:
            what = (f"the run stops before step {then.index + 1} is recorded complete; a resumed run "
                    "('rigctl resume') " + (f"re-runs the warm-up ({warm.sample_s:g} s, step {warm.index + 1}) "
                                            "first, then " if warm is not None else "") +
                    f"runs step {then.index + 1} again")
            plan = ("the run stops; 'rigctl resume' " + (f"re-runs the warm-up ({warm.sample_s:g} s, step "
                                                         f"{warm.index + 1}) first, then step {then.index + 1}"
                                                         if warm is not None else f"runs step {then.index + 1} again"))
        else:
            first = ""
            if chambers:        # they run before the re-warm: it precedes the next measurement
                names = ", ".join(str(s.index + 1) for s in chambers)
                first = (f"step {names} ({chambers[0].kind}) {how}" if len(chambers) == 1 else
                         f"steps {names} (chamber) run") + ", then "
            if measured is None:
                plan = "no warm-up re-runs: only chamber steps follow"
                what = f"{first}no step that measures follows, so the warm-up does not run again"
            elif warm is None:
                plan = "no warm-up to re-run"
                what = f"the procedure has no warm-up to run again; {first}step {measured.index + 1} " + \
                    (how if measured is then else "runs")
            else:
                plan = f"warm-up re-runs ({warm.sample_s:g} s) before step {measured.index + 1}"
                what = (f"{first}the warm-up ({warm.sample_s:g} s, step {warm.index + 1}) runs again"
                        + (" first" if not chambers else "") +
                        f", then step {measured.index + 1} {how if measured is then else 'runs'}")
                self.rewarm = f"the IMU restarted {said}"
        self.rec.add_event(t, "device-restart", event_text("IMU restarted (device time began again: power lost) ",
                                                           *where, "; ", *last, f"; {plan}"))
        self.log("warning", f"the IMU restarted {said} (its device time began again: it lost power, so its "
                            f"turn-on bias is new and it is cold): {''.join(last)}; {what}")

    def _watch_pace(self, t: float) -> None:
        """Say once, early, when rig time runs slower than the clock's speed asks: a clock that
        an in-process emulator sets back (``slipped``, rigctl.clock.ScaledClock) because the host
        cannot compute that fast. Measured over :attr:`pace_window_s` of wall time, on the rig
        time the devices report (``t``: the table's reading; the clock itself runs ahead of
        them by the catch-up in progress, 0.1 s of wall time = 1000 s at 10000x).

        On a clock nobody sets back (a rig on the wire, clock ``scaled``), the devices' time
        itself: when it runs slower than the clock (:func:`slow_rig_speed`) over two windows in a
        row, :func:`slow_rig_message` (kept in :attr:`slow_rig`; a window that then comes out
        short for good stops the run with it)."""
        clock = self.rig.clock
        slipped = getattr(clock, "slipped", None)
        if slipped is None or self.pace_warned:
            return
        wall = time.monotonic()
        imu_t = self._imu_t
        if not math.isnan(imu_t) and (self._pace_origin is None or imu_t < self._pace_origin[1]):
            self._pace_origin = (wall, imu_t)   # the first sample (or a stream whose time began again)
        if self._pace is None:
            self._pace = (wall, t, slipped, imu_t)
            return
        w0, t0, s0, _ = self._pace
        if wall - w0 < self.pace_window_s:
            return
        speed = float(clock.speed)
        achieved = (t - t0) / (wall - w0)
        if slipped > s0 and achieved < PACE_SLOW_FRACTION * speed:
            self.pace_warned = True
            self.log("warning", pace_message(speed, achieved), speed=speed, achieved_speed=achieved)
            self.rec.add_event(t, "clock", f"rig time runs slower than {speed:g}x wall time: "
                                           f"the host computes about {achieved:.1f}x")
            return
        # a clock nobody sets back (a rig on the wire): the devices' time itself runs slower than
        # the clock -- an emulator this machine cannot compute at that speed. Two windows in a
        # row: one stall of the emulator's host (caught up at once after) is not a pace
        slow = self._rig_pace(speed, wall, t) if slipped == 0.0 else None
        self._pace, self._imu_down = (wall, t, slipped, imu_t), False
        if slow is not None and self._pace_slow is not None:
            self.pace_warned = True
            self.slow_rig = self._slow_rig_line(speed, slow, wall)   # the latest window: the pace now
            self.log("warning", self.slow_rig, speed=speed, achieved_speed=slow)
            self.rec.add_event(t, "clock", f"the rig's devices keep time at about {slow:.1f}x wall time, "
                                           f"slower than the run's clock at {speed:g}x")
        self._pace_slow = slow

    def _rig_pace(self, speed: float, wall: float, t: float) -> float | None:
        """:func:`slow_rig_speed` over the pace window in progress (since ``self._pace``, to
        ``wall`` and the table's time ``t``), end to end: on the table's time and on the IMU
        stream's own (its latest sample's time), the slower of the two (a stream that falls behind
        while the table keeps time -- or the reverse -- is the rig's pace all the same). Notes in
        ``self._stream_slower`` whether the stream was the slower."""
        w0, t0, _, imu_t0 = self._pace
        device_s, imu_s = t - t0, self._imu_t - imu_t0
        self._stream_slower = False
        # not across a lost link or a stream whose time began again (an IMU restart): the
        # table's time alone
        if not self._imu_down and imu_s >= 0.0:     # False when either time is unknown (NaN)
            self._stream_slower = imu_s < device_s
            device_s = min(device_s, imu_s)
        return slow_rig_speed(speed, wall - w0, device_s)

    def _slow_rig_line(self, speed: float, achieved: float, wall: float) -> str:
        """:func:`slow_rig_message` for the devices' speed ``achieved`` over a pace window (the
        last :meth:`_rig_pace`). When the IMU stream was the slower, or the table's time stood
        still for :data:`STILL_TABLE_READS` reads or more, the stream's lag is the cause said,
        and the speed stated is the stream's own since its first sample, when higher: a window
        in which the stream stood still (the emulator held back by a host that did not read it)
        measures a stall, not the speed the rig can keep."""
        frozen = self._still_reads >= STILL_TABLE_READS
        if not (frozen or self._stream_slower) or math.isnan(self._imu_t) or self._pace_origin is None:
            return slow_rig_message(speed, achieved)
        w0, imu_t0 = self._pace_origin
        if wall - w0 > 0.0:
            achieved = max(achieved, (self._imu_t - imu_t0) / (wall - w0))
        lag = float(self.rig.clock.now()) - self._imu_t
        return slow_rig_message(speed, achieved, still=(self._still_reads if frozen else 0, lag))

    def _slow_rig_now(self) -> str | None:
        """:func:`slow_rig_message` when the devices' time ran slower than an unslipped clock over
        the pace window in progress (at least half of :attr:`pace_window_s` long), else None."""
        clock, state = self.rig.clock, self.last_state
        if self._pace is None or state is None or getattr(clock, "slipped", None) != 0.0:
            return None
        wall = time.monotonic()
        speed = float(clock.speed)
        slow = (self._rig_pace(speed, wall, float(state.time))
                if wall - self._pace[0] >= 0.5 * self.pace_window_s else None)
        return self._slow_rig_line(speed, slow, wall) if slow is not None else None

    def _poll_chamber(self, t: float) -> None:
        """Read the chamber (at most every ``chamber_poll_s``), record it, keep its trip reason."""
        wall = time.monotonic()
        # the wall-time limit protects a slow link under a fast clock; under the virtual clock
        # (everything in-process) it would make the readings depend on the machine's speed
        wall_limited = not isinstance(self.rig.clock, VirtualClock)
        if t - self._chamber_t < self.chamber_poll_s - 1e-9 or (
                wall_limited and wall - self._chamber_wall < self.chamber_poll_wall_s):
            return
        self._chamber_t, self._chamber_wall = t, wall
        from ..config.chamber import describe_trip
        try:
            state = self.rig.chamber.read()
        except (LinkLost, DeviceFault, OSError) as exc:
            self._chamber_reason = f"chamber link lost: {exc}"
            return
        self.last_chamber = state
        self.rec.append_chamber(state)
        self._chamber_reason = describe_trip(state, self.rig.chamber_band)

    def pump(self, duration: float, period: float) -> TableState:
        """Let ``duration`` seconds pass, polling every ``period``."""
        clock = self.rig.clock
        end = clock.now() + duration
        state = self.poll()
        while (remaining := end - clock.now()) > 1e-9:
            clock.sleep(min(period, remaining))
            state = self.poll()
        return state

    # -- steps ---------------------------------------------------------------------------------
    def command(self, step: Step) -> None:
        table = self.rig.table
        try:
            table.move(step.angles)
            if step.rate_mode:
                table.set_rate(step.rates)
        except (DeviceFault, LinkLost) as exc:
            raise Suspend({"table": f"table refused the demand: {exc}"}) from None

    def settle(self, step: Step) -> float:
        """Wait for the settle criteria; returns the time from command to settled (the run's
        clock), s.

        The hold and the timeout are measured on the table's own time (``TableState.time``, its
        controller's clock on the run's time base), from its first reading after the command:
        they are criteria on the table, which on a real rig runs with the run's clock. On an
        emulated rig it can fall behind it -- the physics waits for the IMU stream's client, or
        for the CPU -- and a timeout on the run's clock then failed a table that had not had the
        time (the wired soaks and 24-position runs at 100x under load: 'did not settle within
        60 s' with the table's time standing still for 70 s of the run's clock).

        The timeout fails the step when the table is outside the criteria at a reading after it;
        a table inside them then finishes its hold first (at most ``hold_s`` more). Otherwise a
        host stall across the timeout -- one poll 0.24 s of wall time late on a clock at 500x is
        120 s of rig time -- failed a table that was in position ('hold time not reached'; seen
        at load 10 on 2 cores, a resumed warm-up at 500x). A table whose time does not advance
        at all for :data:`SETTLE_STILL_TIMEOUTS` timeouts of the run's clock (and at least
        :attr:`still_wall_s` of wall time) fails the step too (a controller that answers with a
        clock that stands still could never time out)."""
        clock = self.rig.clock
        t0 = clock.now()
        first: float | None = None          # the table's time at its first reading, s
        inside_since: float | None = None   # the table's time since which it is inside, s
        advanced = (-math.inf, t0, time.monotonic())  # (the table's latest time, the run's clock, wall)
        timeout = step.settle.timeout_s
        while True:
            state = self.poll()
            now, t_table = clock.now(), float(state.time)
            first = t_table if first is None else first
            if t_table > advanced[0] + 1e-6:    # moved (not a rounding of its time base's offset)
                advanced = (t_table, now, time.monotonic())
            reason = settle_check(state, step)
            if reason is None:
                inside_since = t_table if inside_since is None else inside_since
                if t_table - inside_since >= step.settle.hold_s - 1e-9:
                    return now - t0
            else:
                inside_since = None
                if "fault" in reason:
                    raise RunError(f"step {step.index + 1} ({step.label}): {reason}")
            if t_table - first > timeout and reason is not None:
                raise RunError(
                    f"step {step.index + 1} ({step.label}) did not settle within {timeout:g} s: {reason} "
                    f"[{step.file}:{step.line}] -- check the table, or widen 'settle' windows / timeout")
            if now - advanced[1] > SETTLE_STILL_TIMEOUTS * timeout and \
                    time.monotonic() - advanced[2] > self.still_wall_s:
                raise RunError(
                    f"step {step.index + 1} ({step.label}): the table's time stood still at "
                    f"{advanced[0]:.3f} s for {now - advanced[1]:.0f} s while it settled ({reason or 'inside'}) "
                    f"[{step.file}:{step.line}] -- check the table controller and its link")
            clock.sleep(self.settle_poll_s)

    # -- the climatic chamber ------------------------------------------------------------------
    def _chamber(self, step: Step) -> Any:
        if self.rig.chamber is None:
            raise RunError(f"step {step.index + 1} ({step.label}) needs a climatic chamber, and the "
                           f"rig has none [{step.file}:{step.line}] -- add a 'chamber:' section to the config")
        return self.rig.chamber

    def command_chamber(self, step: Step) -> None:
        """Send a chamber step's set point (and ramp rate) to the chamber."""
        c = step.chamber or {}
        if c.get("setpoint_c") is None:
            return
        try:
            self._chamber(step).set_setpoint(c["setpoint_c"], c.get("rate_c_per_min"))
        except (DeviceFault, LinkLost, OSError) as exc:
            raise Suspend({"chamber": f"chamber refused the set point: {exc}"}) from None
        rate = c.get("rate_c_per_min")
        self.rec.add_event(self.rig.clock.now(), "chamber",
                           f"set point {c['setpoint_c']:g} degC" + (f" at {rate:g} degC/min" if rate else ""))

    def chamber_step(self, step: Step) -> Segment:
        """chamber-set / chamber-ramp: command and go on; chamber-wait: hold the table at the
        step's angles until the chamber's air is within ``air_band_c`` of its set point and the
        IMU's temperature has stayed within ``stable_band_c`` (max - min) for ``stable_for_s``."""
        clock = self.rig.clock
        self._chamber(step)
        t0 = clock.now()
        first = self.rec.n_imu
        if step.kind != "chamber-wait":
            self.command_chamber(step)
            self.poll()
        else:
            c = step.chamber
            self.command_chamber(step)
            self.command(step)
            self.settle(step)
            self._temps = deque()
            first = self.rec.n_imu
            self.sampling_from = first
            self._sampled = True
            t_wait = clock.now()
            try:
                while True:
                    clock.sleep(self.sample_poll_s)
                    self.poll()
                    now = clock.now()
                    while self._temps and self._temps[0][0] < now - c["stable_for_s"]:
                        self._temps.popleft()
                    ch = self.last_chamber
                    air_ok = ch is not None and abs(ch.air_c - ch.setpoint_c) <= c["air_band_c"] and \
                        (c["setpoint_c"] is None or abs(ch.setpoint_c - c["setpoint_c"]) < 1e-6)
                    if self._temps and air_ok and now - t_wait >= c["stable_for_s"] - 1e-9:
                        spread = max(x[2] for x in self._temps) - min(x[1] for x in self._temps)
                        if spread <= c["stable_band_c"]:
                            break
                    if now - t_wait > c["timeout_s"]:
                        what = (f"air {ch.air_c:.2f} degC, set point {ch.setpoint_c:.2f} degC"
                                if ch is not None else "no chamber reading")
                        raise RunError(f"step {step.index + 1} ({step.label}): temperature not stable "
                                       f"within {c['timeout_s']:g} s ({what}) [{step.file}:{step.line}]")
            finally:
                self._temps = None
        t1 = clock.now()
        s = self.last_state
        nan3 = np.full(3, np.nan)
        seg = Segment(kind=step.kind, label=step.label, step=step.index, first_sample=first,
                      last_sample=self.rec.n_imu, t_start=t0, t_end=t1, settle_time=math.nan,
                      commanded_angle=step.angles, commanded_rate=np.zeros(3),
                      measured_angle=s.angle if s is not None else nan3,
                      measured_rate=s.rate if s is not None else nan3)
        self.rec.add_segment(seg)
        self.sampling_from = None
        return seg

    def execute(self, step: Step) -> Segment:
        """Command, settle, discard the transient, sample, and record the segment."""
        if step.kind in CHAMBER_KINDS:
            self.current_step, self._sampled = step, False
            try:
                return self.chamber_step(step)
            finally:
                self.current_step = None
        self.current_step = step
        self.sampling_from = None
        self._sampled = False
        # recent blocks as (row of the block's first sample, its IMU times): flat memory
        self._track, self._win_start, self._first_row = deque(maxlen=256), None, None
        clock = self.rig.clock
        if step.prompt:
            self.log("prompt", step.prompt)
        self.command(step)
        settle_time = self.settle(step)
        if step.discard_s > 0:
            self.pump(step.discard_s, self.settle_poll_s)
        t_start = clock.now()
        self._win_start = t_start
        for row0, times in self._track:
            i = int(np.searchsorted(times, t_start - TIME_EPS))
            if i < len(times):
                self._first_row, self._first_time = row0 + i, float(times[i])
                break
        self.sampling_from = self.rec.n_imu
        self._sampled = True
        if step.prompt and self.rig.operator is not None:
            self.rig.operator.prompt(step, t_start, step.sample_s)
        n_polls, sum_angle, sum_rate = 0, np.zeros(3), np.zeros(3)  # running sums: flat memory
        end = t_start + step.sample_s
        while (remaining := end - clock.now()) > 1e-9:
            clock.sleep(min(self.sample_poll_s, remaining))
            s = self.poll()
            n_polls += 1
            sum_angle += s.angle
            sum_rate += s.rate
        # the window is the one the step asked for: with a clock that runs with wall time (a
        # wired rig, scaled x100 in the emulated HIL runs) the last sleep and poll end later than
        # ``end`` by their wall time x speed (20 ms of a loaded host = 2 s of rig time at 100x);
        # the samples after ``end`` belong to no window, as under the virtual clock
        t_end = min(clock.now(), end)
        self._tail_sus = None
        first, last, t_last = self._window_rows(t_start, t_end)
        tail, self._tail_sus = self._tail_sus, None
        if tail is None:
            self._check_window(step, t_start, t_end, first, last, t_last)
        else:   # tripped while the window's last samples were awaited: they decide
            want, n, _, covered, short = self._window_cover(t_start, t_end, first, last, t_last)
            whole = self._tail_whole(tail, want, n, short)
            self._tail_restart_said(step, complete=whole)
            if not whole:   # they stopped inside it: as a trip while sampling
                self._tail_covered = covered
                raise tail
            self.rec.add_event(clock.now(), "info", event_text(
                f"step {step.index + 1} (", Elide(step.label), f"): {', '.join(tail.reasons)} tripped "
                f"after its window, whose {n} samples cover it ({covered:.1f} s of {want:g} s): "
                "the step is complete; the run pauses before the next step"))
        ang = sum_angle / n_polls if n_polls else self.last_state.angle
        rate = sum_rate / n_polls if n_polls else self.last_state.rate
        seg = Segment(kind=step.kind, label=step.label, step=step.index, first_sample=first,
                      last_sample=last, t_start=t_start, t_end=t_end, settle_time=settle_time,
                      commanded_angle=step.angles, commanded_rate=np.nan_to_num(step.rates, nan=0.0),
                      measured_angle=ang, measured_rate=rate)
        self.rec.add_segment(seg)
        self.current_step = None
        self.sampling_from = None
        if tail is not None:
            tail.segment = seg
            raise tail
        return seg

    def _track_block(self, row0: int, times: np.ndarray) -> None:
        self._track.append((row0, times))
        if self._win_start is not None and self._first_row is None:
            i = int(np.searchsorted(times, self._win_start - TIME_EPS))
            if i < len(times):
                self._first_row, self._first_time = row0 + i, float(times[i])

    def _window_rows(self, t_start: float, t_end: float) -> tuple[int, int, float]:
        """Rows [first, last) of the recorded IMU samples whose IMU time lies in [t_start, t_end),
        and the IMU time of the last of them (nan when there is none), s.

        Samples reach the engine with some latency (a serial link, a decoder batch), so the
        window is cut by the samples' own times, not by which poll delivered them; the engine
        keeps polling until a sample at or after ``t_end`` has arrived (bounded wait: 2 s of rig
        time, at least :data:`WINDOW_WAIT_WALL_S` of wall time). A suspender that trips meanwhile
        is kept in ``_tail_sus`` and the wait goes on (:meth:`execute` decides with the samples)."""
        clock = self.rig.clock
        speed = float(getattr(clock, "speed", 1.0))
        wait_until = clock.now() + max(2.0, 4 * self.sample_poll_s, WINDOW_WAIT_WALL_S * speed)
        self._awaiting_tail, self._tail_restart = True, None
        try:
            while (not self._track or self._track[-1][1][-1] < t_end - TIME_EPS) and clock.now() < wait_until:
                clock.sleep(self.settle_poll_s)
                try:
                    self.poll()
                except Suspend as sus:  # the window is over: its samples decide (execute), so the
                    if self._tail_sus is None:  # wait goes on for those still in flight; a trip
                        self._tail_sus = sus    # seen later in it joins the first (the pause names it)
                    else:
                        self._tail_sus.merge(sus)
        except BaseException:       # the run ends (abort, fault: only a Suspend is caught above)
            self._tail_restart_said(self.current_step, complete=False, stopping=True)
            raise
        finally:
            self._awaiting_tail = False
        track, first = self._track, self._first_row
        self._track, self._win_start, self._first_row = None, None, None
        if first is None:  # no sample inside the window arrived
            return self.rec.n_imu, self.rec.n_imu, math.nan
        last = self.rec.n_imu
        for row0, times in track:
            i = int(np.searchsorted(times, t_end - TIME_EPS))
            if i < len(times):
                last = row0 + i
                break
        last = max(first, last)
        t_last = math.nan
        for row0, times in reversed(track):   # the block holding row last - 1 (recent: kept)
            if row0 <= last - 1 < row0 + len(times):
                t_last = float(times[last - 1 - row0])
                break
        return first, last, t_last

    def _window_cover(self, t_start: float, t_end: float, first: int, last: int,
                      t_last: float) -> tuple[float, int, float, float, bool]:
        """(window asked for s, samples n, rate Hz (0: unknown), time covered s, short) of the
        window's rows [first, last) (see :meth:`_check_window`); forgets the window's first time."""
        want = t_end - t_start
        n = last - first
        rate = self.imu_rate_hz
        if rate <= 0.0:    # no configured rate: the window's own mean sample spacing
            rate = (n - 1) / (t_last - self._first_time) if n > 1 and t_last > self._first_time else 0.0
        period = 1.0 / rate if rate > 0.0 else 0.0
        covered = 0.0 if n == 0 or math.isnan(t_last) else t_last - self._first_time + period
        self._first_time = None
        short = not (n > 0 and covered >= want - SHORT_WINDOW_TOL_PERIODS * period - TIME_EPS)
        return want, n, rate, covered, short

    def _tail_whole(self, tail: Suspend, want: float, n: int, short: bool) -> bool:
        """Whether a window whose last samples were awaited when ``tail`` tripped is whole: its
        samples cover it (:meth:`_window_cover`) and, when ``imu-gap`` tripped (a counter gap may
        lie inside it), it holds the samples its length takes at the configured rate (no rate
        configured: it cannot tell, and is not)."""
        if short:
            return False
        if "imu-gap" not in tail.reasons:
            return True
        return self.imu_rate_hz > 0.0 and n >= want * self.imu_rate_hz - SHORT_WINDOW_TOL_PERIODS

    def _check_window(self, step: Step, t_start: float, t_end: float, first: int, last: int,
                      t_last: float) -> None:
        """Refuse a window whose samples cover less than it: raise Suspend (the step is sampled
        again, :meth:`run`) or, after :data:`SHORT_WINDOW_TRIES` short attempts of the step,
        RunError (the run stops; resumable as any interrupted run).

        Covered time: ``t_last - t_first + T`` (T = 1 / the IMU rate: each sample stands for one
        period); short when ``covered < (t_end - t_start) - SHORT_WINDOW_TOL_PERIODS * T``, or
        when no sample arrived at all. Samples dropped inside the window (counter gaps) do not
        shorten it: they are recorded as gaps, and a long one trips the 'imu-gap' suspender."""
        want, n, rate, covered, short = self._window_cover(t_start, t_end, first, last, t_last)
        if not short:
            return
        tries = self.short_windows[step.index] = self.short_windows.get(step.index, 0) + 1
        expected = f" of {want * rate:.0f}" if rate > 0.0 else ""
        what = (f"step {step.index + 1} ({step.label}): the IMU samples cover {covered:.1f} s of "
                f"the {want:g} s window ({n}{expected} samples) -- the IMU stream lags or stopped")
        self.rec.add_event(self.rig.clock.now(), "short-window", f"{what} (attempt {tries})")
        if tries >= SHORT_WINDOW_TRIES:
            self._cut_off(step)
            todo = self.slow_rig or self._slow_rig_now() or "check the IMU link, then 'rigctl resume' the run"
            raise RunError(f"{what}; still short after {tries} attempts, run stopped "
                           f"[{step.file}:{step.line}] -- {todo}")
        raise Suspend({"imu-window": f"{what}; sampling it again"})

    def run(self, steps: list[Step], start: int = 0,
            on_step: Callable[[Step, Segment], None] | None = None,
            stop_first: str | None = None) -> list[Segment]:
        """Execute ``steps[start:]`` (solve steps are skipped: they run after the recording).

        A suspension pauses the run (see :meth:`suspend`) and the interrupted step then runs
        again from its start. ``stop_first`` (a resumed run): stop the table before any motion,
        see :meth:`stop_first`."""
        segments = []
        motion = self._motion = [s for s in steps[start:] if s.is_motion]
        if self.states.state == "idle":
            self.states.to("running", f"{len(motion)} steps to run")
        if stop_first is not None:
            self.stop_first(stop_first)
        before = [s for s in steps[:start] if s.kind in ("chamber-set", "chamber-ramp")]
        if start > 0 and before and self.rig.chamber is not None:
            # a resumed run: the clean-up of the cut-off session put the chamber at its safe
            # set point; the last set point commanded before the resume point holds again
            self.log("info", f"resuming: chamber set point of step {before[-1].index + 1} again")
            self.command_chamber(before[-1])
        self._warmup = next((s for s in steps if s.kind == "warmup"), None)
        n = 0
        while n < len(motion):
            step = motion[n]
            if self.deferred_pause is not None:  # due now, between two steps: nothing is cut off
                reason, self.deferred_pause = self.deferred_pause, None
                self.suspenders.operator = reason
                try:
                    self.poll()
                except Suspend as sus:
                    self.suspend(step, sus, between_steps=True)
                    continue
            if self.rewarm is not None and step.kind not in CHAMBER_KINDS:
                if step.kind == "warmup":          # the warm-up itself: whole, from its start
                    self.warmup_done.pop(step.index, None)
                    self.rewarm = None
                elif self._warmup is None:
                    self.rewarm = None
                else:
                    try:
                        self._rewarm(self._warmup, step)
                    except Suspend as sus:
                        if sus.segment is None:     # cut off: it runs again
                            self.suspend(self._warmup, sus)
                        else:                       # complete; the pause comes before the step
                            self.suspend(step, sus, between_steps=True)
                    continue
            self.log("step", f"[{n + 1}/{len(motion)}] {step.describe()}", echo=False)
            self.progress.step_started(step)
            after: Suspend | None = None
            try:
                seg = self.execute(self._warmup_left(step))
            except Suspend as sus:
                if sus.segment is None:
                    self.suspend(step, sus)
                    continue
                seg, after = sus.segment, sus     # the step is complete; the pause comes next
            self.progress.step_finished(step, seg)
            self._last_done = step
            if step.kind == "warmup":     # done: time kept from its cut-off attempts is spent
                self.warmup_done.pop(step.index, None)
            segments.append(seg)
            if on_step:
                on_step(step, seg)
            n += 1
            if after is not None and n < len(motion):
                self.suspend(motion[n], after, between_steps=True)
            elif after is not None:
                self.log("warning", f"{', '.join(after.reasons)} after the last window: {after}; "
                                    "every step is complete")
        return segments

    def _rewarm(self, warm: Step, before: Step) -> None:
        """Run the procedure's warm-up ``warm`` again (after :attr:`rewarm`: the IMU restarted),
        recorded as a complete ``warmup`` segment of its step index, then clear :attr:`rewarm`;
        ``before``: the step that follows it. Raises Suspend as :meth:`execute` does."""
        self.log("step", f"re-warm before step {before.index + 1} ({before.label}): {warm.describe()}", echo=False)
        self.rec.add_event(self.rig.clock.now(), "info", event_text(
            f"re-warm: step {warm.index + 1} (", Elide(warm.label), f", {warm.sample_s:g} s) again, ",
            Elide(str(self.rewarm)), f"; then step {before.index + 1} (", Elide(before.label), ")"))
        why, self.rewarm, self._rewarm_before = self.rewarm, None, before  # a restart from here on
        try:                                                                 # sets it anew
            self.execute(self._warmup_left(warm))
        except Suspend as sus:
            if sus.segment is None and self.rewarm is None:    # cut off: it runs again
                self.rewarm = why
            raise
        finally:
            self._rewarm_before = None
        self.warmup_done.pop(warm.index, None)

    # -- suspension ------------------------------------------------------------------------------
    #: suspenders after which the IMU may have been without power: a warm-up starts over
    POWER_SUSPENDERS = ("imu-link", "imu-gap", "imu-window", "imu-restart")

    def _warmup_left(self, step: Step) -> Step:
        """A warm-up interrupted before with the IMU powered all along runs only what is left."""
        done = self.warmup_done.get(step.index, 0.0)
        if step.kind != "warmup" or done <= 0.0:
            return step
        left = max(0.0, step.sample_s - done)
        self.log("info", f"warm-up: {done:.1f} s already done with the IMU powered; {left:.1f} s left")
        self.rec.add_event(self.rig.clock.now(), "info", event_text(
            f"step {step.index + 1} (", Elide(step.label), f"): {done:.1f} s of warm-up kept, {left:.1f} s left"))
        return replace(step, sample_s=left)

    def _stop_table(self, wait_s: float = 5.0, seen: PauseTrips | None = None) -> None:
        """Stop the table (rate zero, mode off) and record it until still or ``wait_s``. In a
        pause (``seen``: its suspenders so far) a suspender that trips meanwhile is
        recorded and named as in the pause's own polls (:meth:`_note_trips`)."""
        try:
            self.rig.table.stop()
        except Exception as exc:  # noqa: BLE001 - a faulted / unreachable table: keep pausing
            self.log("warning", f"could not command the table to stop: {exc}")

        def poll() -> TableState:
            state = self.poll(check=False)
            if seen is not None:
                self._note_trips(seen)
            return state
        self._wait_still(poll, wait_s)

    def _wait_still(self, poll: Callable[[], TableState], wait_s: float) -> bool:
        """After a stop command: ``poll()`` until the table reports no motion (True), or until it
        has moved on for ``wait_s`` of its own time since its first reading (False).

        Measured on the table's time (``TableState.time``), as :meth:`settle` measures its
        timeout: an emulated table can fall behind the run's clock (its physics starved of CPU),
        and ``wait_s`` of the run's clock -- 20 ms of wall time for 2 s at 100x -- ended the end of
        run's safe state while the table was still slowing down ('the table still reports motion
        after the stop command', a wired run at load ~20 failed on it). A table whose time stands
        still (a controller that answers with a frozen clock) ends the wait after
        :data:`SETTLE_STILL_TIMEOUTS` x ``wait_s`` of the run's clock and :attr:`still_wall_s` of
        wall time, as in :meth:`settle`; a table that cannot be read at all (the poll keeps its
        last state: link lost) after ``wait_s`` of the run's clock, as before."""
        clock = self.rig.clock
        t0 = clock.now()
        first: float | None = None      # the table's time at its first reading, s
        advanced = (-math.inf, t0, time.monotonic())  # (the table's latest time, the run's clock, wall)
        while True:
            before = self.last_state
            state = poll()
            if not state.any_has(AxisStatus.MOVING):
                return True
            now = clock.now()
            if state is before or not math.isfinite(float(state.time)):   # not read: the run's clock
                if now - t0 >= wait_s:
                    return False
            else:
                t_table = float(state.time)
                first = t_table if first is None else first
                if t_table > advanced[0] + 1e-6:
                    advanced = (t_table, now, time.monotonic())
                if t_table - first >= wait_s:
                    return False
                if now - advanced[1] > SETTLE_STILL_TIMEOUTS * wait_s and \
                        time.monotonic() - advanced[2] > self.still_wall_s:
                    return False
            clock.sleep(self.settle_poll_s)

    def suspend(self, step: Step, sus: Suspend, between_steps: bool = False) -> None:
        """Pause on a tripped suspender; return once all have been clear for the hold time.

        The step in flight is written as an ``incomplete`` segment when it had started
        sampling, and always named in an event with its IMU sample range. ``between_steps``
        (a deferred pause): ``step`` has not started; nothing is cut off.

        A warm-up cut off while sampling keeps the time it had sampled (the re-run samples only
        what is left) unless a suspender that may mean a power loss of the IMU tripped
        (:data:`POWER_SUSPENDERS`): then the whole warm-up runs again. Time spent paused does
        not count."""
        clock, rec = self.rig.clock, self.rec
        if step.kind == "warmup" and self.sampling_from is not None:
            if set(sus.reasons) & set(self.POWER_SUSPENDERS):
                if self.warmup_done.pop(step.index, None):
                    self.log("info", "warm-up starts over: the IMU may have lost power")
            elif self._tail_covered is not None or self._win_start is not None:
                # the time sampled; cut off while its last samples were awaited: the time they cover
                done = self._tail_covered if self._tail_covered is not None else clock.now() - self._win_start
                self.warmup_done[step.index] = self.warmup_done.get(step.index, 0.0) + done
        self._tail_covered = None
        self.n_suspensions += 1
        names = ", ".join(sus.reasons)
        message = str(sus)
        self.states.to("pausing", message)
        self.log("warning", f"suspended ({names}): {message}", suspenders=sus.reasons)
        rec.add_event(clock.now(), "suspend", f"{names}: {message}")
        if not between_steps:
            self._cut_off(step)
        self.sampling_from = None
        seen = PauseTrips.begin(sus.reasons)
        self._stop_table(seen=seen)
        self.states.to("paused", message)
        hold = self.suspenders.s.hold_s
        t0 = clock.now()
        while True:
            clock.sleep(self.pause_poll_s)
            self.poll(check=False)
            now = clock.now()
            self._note_trips(seen)
            if not self.suspenders.active and self.suspenders.clear_for(now) >= hold - 1e-9:
                break
            if self.max_pause_s is not None and now - t0 > self.max_pause_s:
                raise RunError(f"paused for more than {self.max_pause_s:g} s: "
                               f"{'; '.join(self.suspenders.active.values()) or message}")
        for name, n in sorted(seen.again.items()):
            if n > PAUSE_RETRIP_EVENTS:
                rec.add_event(now, "info", f"{name} tripped {n - PAUSE_RETRIP_EVENTS} more times in this pause "
                                           f"than the {PAUSE_RETRIP_EVENTS} recorded one by one")
        parts = (f"{', '.join(sorted(seen.names))} clear for {hold:g} s after {now - t0:.1f} s paused; "
                 f"{'starting' if between_steps else 're-running'} step {step.index + 1} (", Elide(step.label), ")")
        text = "".join(parts)
        rec.add_event(now, "resume", event_text(*parts))
        self.log("info", f"resuming: {text}")
        self.states.to("running", text)

    def _note_trips(self, seen: PauseTrips) -> None:
        """After a poll in a pause: record each suspender that trips now -- tripped at this poll,
        clear at the one before -- as a ``suspend`` event, as the trip that began it: one the
        pause does not name yet, and one that trips again (a second data gap names its own
        counters; at most :data:`PAUSE_RETRIP_EVENTS` such events per suspender, the rest
        counted at the resume). Before, a suspender the pause already named got no event when it
        tripped again: a second gap's counters were in no event. ``seen`` is updated."""
        active = self.suspenders.active
        trips = sorted(set(active) - seen.active)
        seen.active = set(active)
        record = []
        for k in trips:
            if k in seen.names:
                seen.again[k] = seen.again.get(k, 0) + 1
                if seen.again[k] > PAUSE_RETRIP_EVENTS:
                    continue
            record.append(k)
        seen.names |= set(trips)
        if record:
            text = "; ".join(active[k] for k in record)
            self.log("warning", f"also: {text}")
            self.rec.add_event(self.rig.clock.now(), "suspend", f"{', '.join(record)}: {text}")

    def _cut_off(self, step: Step) -> None:
        """Write the step in flight as an ``incomplete`` segment (when it had started sampling)
        and name it in an event with its IMU sample range: its rows belong to no segment."""
        clock, rec = self.rig.clock, self.rec
        if self.sampling_from is not None:
            first, last = self.sampling_from, rec.n_imu
            s = self.last_state
            rec.add_segment(Segment(
                kind=step.kind, label=step.label, step=step.index, first_sample=first,
                last_sample=last, t_start=clock.now(), t_end=clock.now(), settle_time=math.nan,
                commanded_angle=step.angles, commanded_rate=np.nan_to_num(step.rates, nan=0.0),
                measured_angle=s.angle if s is not None else np.full(3, np.nan),
                measured_rate=s.rate if s is not None else np.full(3, np.nan), status="incomplete"))
            rec.add_event(clock.now(), "incomplete", event_text(
                f"step {step.index + 1} (", Elide(step.label), f") cut off: IMU rows [{first}, {last}) "
                "excluded; the step re-runs"))
        else:
            rec.add_event(clock.now(), "incomplete", event_text(
                f"step {step.index + 1} (", Elide(step.label), ") cut off before sampling; re-runs"))
        self.sampling_from = None

    def stop_first(self, why: str, wait_s: float = 30.0) -> None:
        """Before the first motion of a resumed run: record how the cut-off left the table (a
        crash cannot stop it: it may still hold a position or spin at a rate), command it to stop
        (rate zero, mode off) and wait until it stands still, so the next step starts from rest
        (its move then re-homes the table to the step's angles)."""
        clock = self.rig.clock
        names = ("outer", "middle", "inner")
        try:
            state = self.rig.table.read()
        except Exception as exc:  # noqa: BLE001 - a fault here pauses at the first step instead
            found = f"table state unreadable ({exc})"
        else:
            servo = [n for n, w in zip(names, state.status) if int(w) & AxisStatus.SERVO_ON]
            rates = ", ".join(f"{n} {math.degrees(r):+.3f} deg/s" for n, r in zip(names, state.rate))
            found = (f"table found {'moving' if state.any_has(AxisStatus.MOVING) else 'still'} "
                     f"({rates}; servo {'on: ' + ', '.join(servo) if servo else 'off'})")
        self.log("info", f"{why}: {found}; commanding a stop (rate zero, mode off) before any motion")
        self.rec.add_event(clock.now(), "safe-state", f"{why}: {found}; stop commanded before any motion")
        self._stop_table(wait_s)
        state = self.last_state
        if state is not None and not state.any_has(AxisStatus.MOVING):
            self.rec.add_event(clock.now(), "safe-state", "table stopped, servo off; resuming")

    def safe_state(self, wait_s: float = 2.0) -> bool:
        """Command the table to stop (rate zero, mode off), then record its state until it is
        still or ``wait_s`` has passed. Returns True when the table reported standing still.
        Never raises: the caller still has to close the file. The chamber (if any) goes to its
        safe set point first."""
        self.abort_requested = None
        if self.rig.chamber is not None:
            try:
                self.rig.chamber.stop()
                self.rec.add_event(self.rig.clock.now(), "safe-state", "chamber at its safe set point")
            except Exception as exc:  # noqa: BLE001 - reported; the table must still be stopped
                self.log("error", f"could not put the chamber at its safe set point: {exc}")
        try:
            self.rig.table.stop()
        except Exception as exc:  # noqa: BLE001 - reported, the caller still closes the file
            self.log("error", f"could not stop the table: {exc}")
            return False
        if self.open_interlocks and hasattr(self.rig.table, "open_interlock"):
            try:
                self.rig.table.open_interlock()
                self.rec.add_event(self.rig.clock.now(), "safe-state", "interlocks opened")
            except Exception as exc:  # noqa: BLE001
                self.log("error", f"could not open the interlocks: {exc}")
        clock = self.rig.clock
        try:
            if self._wait_still(lambda: self.poll(check=False, safe_state=True), wait_s):
                self.rec.add_event(clock.now(), "safe-state", "table stopped, servo off")
                return True
            self.log("error", f"the table still reports motion after the stop command ({wait_s:g} s of "
                              "its time)")
            return False
        except Exception as exc:  # noqa: BLE001
            self.log("error", f"could not read the table after stopping it: {exc}")
            return False
