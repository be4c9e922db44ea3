"""The engine: executes a compiled plan of steps against a rig, recording everything.

The engine owns no hardware: it is handed devices that follow the small protocols of
:mod:`rigctl.devices` and a clock. For every step it commands the table, waits until the table
has *settled* (the controller reports in position / at rate AND every axis stayed inside the
step's position and rate windows for the hold time), discards the transient, samples for the
step's window, and writes a segment record. It never samples before the hold criteria are met;
a settle timeout stops the run with a message naming the step and what was out of window.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .devices import AxisStatus, Clock, Imu, PulseSource, TableState, Turntable
from .procedure import Step
from .recorder import Recorder, Segment


class RunError(Exception):
    """A failure at run time (settle timeout, device fault)."""


class Interrupted(Exception):
    """The run was interrupted (SIGINT / SIGTERM / abort)."""


@dataclass
class Rig:
    """The devices a run talks to, and the clock of their time base."""

    table: Turntable
    imu: Imu
    pulses: PulseSource
    clock: Clock
    description: str = ""


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
        if status & AxisStatus.FAULT:
            return f"axis {i + 1} reports a fault (status 0x{status:04x})"
        flag = AxisStatus.AT_RATE if rate_axes[i] else AxisStatus.TARGET_REACHED
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
                 sample_poll_s: float = 0.5, log: Callable[[str, str], None] | None = None) -> None:
        self.rig, self.rec = rig, recorder
        self.settle_poll_s, self.sample_poll_s = settle_poll_s, sample_poll_s
        self.log = log or (lambda kind, msg: None)
        self.abort_requested: str | None = None
        self.last_state: TableState | None = None
        self.current_step: Step | None = None

    def request_abort(self, reason: str = "interrupted") -> None:
        """Ask the run to stop at the next poll (safe to call from a signal handler)."""
        self.abort_requested = reason

    # -- polling -------------------------------------------------------------------------------
    def poll(self) -> TableState:
        """Read every device once and record what came in."""
        self.rec.append_imu(self.rig.imu.read())
        self.rec.append_pulses(self.rig.pulses.read())
        state = self.rig.table.read()
        self.rec.append_table(state)
        self.last_state = state
        if self.abort_requested:
            raise Interrupted(self.abort_requested)
        return state

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
        table.move(step.angles)
        if step.rate_mode:
            table.set_rate(step.rates)

    def settle(self, step: Step) -> float:
        """Wait for the settle criteria; returns the time from command to settled, s."""
        clock = self.rig.clock
        t0 = clock.now()
        inside_since: float | None = None
        while True:
            state = self.poll()
            now = clock.now()
            reason = settle_check(state, step)
            if reason is None:
                inside_since = now if inside_since is None else inside_since
                if now - inside_since >= step.settle.hold_s - 1e-9:
                    return now - t0
            else:
                inside_since = None
                if "fault" in reason:
                    raise RunError(f"step {step.index + 1} ({step.label}): {reason}")
            if now - t0 > step.settle.timeout_s:
                raise RunError(
                    f"step {step.index + 1} ({step.label}) did not settle within "
                    f"{step.settle.timeout_s:g} s: {reason or 'hold time not reached'} "
                    f"[{step.file}:{step.line}] -- check the table, or widen 'settle' windows / timeout")
            clock.sleep(self.settle_poll_s)

    def execute(self, step: Step) -> Segment:
        """Command, settle, discard the transient, sample, and record the segment."""
        self.current_step = step
        clock = self.rig.clock
        if step.prompt:
            self.log("prompt", step.prompt)
        self.command(step)
        settle_time = self.settle(step)
        if step.discard_s > 0:
            self.pump(step.discard_s, self.settle_poll_s)
        first = self.rec.n_imu
        t_start = clock.now()
        states = []
        end = t_start + step.sample_s
        while (remaining := end - clock.now()) > 1e-9:
            clock.sleep(min(self.sample_poll_s, remaining))
            states.append(self.poll())
        last = self.rec.n_imu
        ang = np.mean([s.angle for s in states], axis=0) if states else self.last_state.angle
        rate = np.mean([s.rate for s in states], axis=0) if states else self.last_state.rate
        seg = Segment(kind=step.kind, label=step.label, step=step.index, first_sample=first,
                      last_sample=last, t_start=t_start, t_end=clock.now(), settle_time=settle_time,
                      commanded_angle=step.angles, commanded_rate=np.nan_to_num(step.rates, nan=0.0),
                      measured_angle=ang, measured_rate=rate)
        self.rec.add_segment(seg)
        self.current_step = None
        return seg

    def run(self, steps: list[Step], start: int = 0,
            on_step: Callable[[Step, Segment], None] | None = None) -> list[Segment]:
        """Execute ``steps[start:]`` (solve steps are skipped: they run after the recording)."""
        segments = []
        motion = [s for s in steps[start:] if s.is_motion]
        for n, step in enumerate(motion, 1):
            self.log("step", f"[{n}/{len(motion)}] {step.describe()}")
            seg = self.execute(step)
            segments.append(seg)
            if on_step:
                on_step(step, seg)
        return segments

    def safe_state(self, wait_s: float = 2.0) -> bool:
        """Command the table to stop (rate zero, mode off), then record its state until it is
        still or ``wait_s`` has passed. Returns True when the table reported standing still.
        Never raises: the caller still has to close the file."""
        self.abort_requested = None
        try:
            self.rig.table.stop()
        except Exception as exc:  # noqa: BLE001 - reported, the caller still closes the file
            self.log("error", f"could not stop the table: {exc}")
            return False
        clock = self.rig.clock
        t0 = clock.now()
        try:
            while True:
                state = self.poll()
                if not state.any_has(AxisStatus.MOVING):
                    self.rec.add_event(clock.now(), "safe-state", "table stopped, servo off")
                    return True
                if clock.now() - t0 >= wait_s:
                    self.log("error", "the table still reports motion after the stop command")
                    return False
                clock.sleep(self.settle_poll_s)
        except Exception as exc:  # noqa: BLE001
            self.log("error", f"could not read the table after stopping it: {exc}")
            return False
