"""Helpers for the hardware-in-the-loop tests: emulated hardware + wired config + a run."""
from __future__ import annotations

import io
import math
import time
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import yaml

from rigctl.config.config import load_config
from rigctl.engine.procedure import load_procedure
from rigctl.progress import NullProgress
from rigctl.run.runner import RunOptions, run_procedure
from rigctl.sim.hardware import start_hardware
from rigctl.sim.wire_config import write_wire_config

from helpers import SLOW_NOISE_KEYS, white_noise_only  # noqa: F401  (white_noise_only: re-exported)

ROOT = Path(__file__).resolve().parent.parent
SIM = ROOT / "configs" / "sim.yaml"


def white_sim(tmp: Path) -> Path:
    """configs/sim.yaml on white noise only (its slow terms B and K zeroed): the runs here are
    checked against the declared model, and against each other, at white-noise tolerances."""
    d = yaml.safe_load(SIM.read_text())
    d["imu"]["sim"].update({k: 0.0 for k in SLOW_NOISE_KEYS})
    p = tmp / "sim-white.yaml"
    p.write_text(yaml.safe_dump(d))
    return p


def sim_config(tmp: Path, **imu: Any):
    """configs/sim.yaml on white noise only (:func:`white_sim`), with ``imu`` keys changed
    (e.g. rate_hz=2000)."""
    d = yaml.safe_load(white_sim(tmp).read_text())
    d["imu"].update(imu)
    p = tmp / "physics.yaml"
    p.write_text(yaml.safe_dump(d))
    return load_config(p), d


@contextmanager
def hardware(tmp: Path, speed: float, **kw: Any):
    cfg, raw = sim_config(tmp)
    hw = start_hardware(cfg, speed, link_dir=tmp / "ports", **kw)
    try:
        yield hw, raw
    finally:
        hw.close()


def run(proc: str | Path, cfg_path: Path, out: Path, params: dict[str, str], options: RunOptions | None = None):
    cfg = load_config(cfg_path)
    p = load_procedure(ROOT / "procedures" / proc, params, cfg.limits)
    res = run_procedure(p, cfg, out, console=io.StringIO(), install_signals=False, options=options)
    assert res.exit_code == 0, res.message
    return res, cfg


#: a point of a run: a condition on (the engine, the :class:`RunPoints` watching it), checked at
#: every poll of the engine and at the start of every step
RunPoint = Callable[[Any, "RunPoints"], bool]


def _finished(points: RunPoints, kind: str) -> int:
    return sum(seg.kind == kind for seg in points.done)


def sampling(kind: str, after_samples: int = 0, finished: int = 0) -> RunPoint:
    """The poll at which a ``kind`` step (warmup, orientation, ...) has sampled ``after_samples``
    IMU samples of its window, once ``finished`` segments of that kind have been finished -- a
    poll inside the window on the run's clock: samples arrive with latency, and one that brings
    the count only while the engine awaits the window's last samples is past the window (a cable
    pulled there no longer cuts the step off: rigctl.engine.engine.Engine.execute)."""
    def at(engine, points: RunPoints) -> bool:
        step = engine.current_step
        return (points.starting is None and step is not None and step.kind == kind
                and engine.sampling_from is not None and engine.rec.n_imu - engine.sampling_from >= after_samples
                and engine._win_start is not None and engine.rig.clock.now() < engine._win_start + step.sample_s
                and _finished(points, kind) >= finished)
    return at


def starting(kind: str, finished: int = 0) -> RunPoint:
    """The start of a ``kind`` step, before its command, once ``finished`` segments of that kind
    have been finished."""
    def at(engine, points: RunPoints) -> bool:
        return points.starting is not None and points.starting.kind == kind and _finished(points, kind) >= finished
    return at


class RunPoints(NullProgress):
    """A progress display that acts at defined points of a run instead of showing anything: each
    ``(point, action)`` fires once, the first time its point holds, in the engine's thread
    (``update`` runs at every poll, ``step_started`` before every step's command). ``fired``:
    (index, the run's rig time s) of those that did; ``done``: the segments finished so far;
    ``starting``: the step being started (None at a poll)."""

    def __init__(self, actions: list[tuple[RunPoint, Callable[[], Any]]]) -> None:
        super().__init__()
        self.actions = actions
        self.engine: Any = None
        self.done: list = []
        self.fired: list[tuple[int, float]] = []
        self.starting: Any = None

    def on_engine(self, engine: Any) -> None:
        self.engine = engine if engine is not None else self.engine

    def step_started(self, step: Any) -> None:
        self.starting = step
        try:
            self._check(self.engine.rig.clock.now() if self.engine is not None else math.nan)
        finally:
            self.starting = None

    def step_finished(self, step: Any, segment: Any = None) -> None:
        if segment is not None:
            self.done.append(segment)

    def update(self, now_s: float, table_state: Any = None, n_imu_samples: int | None = None,
               dropped: int | None = None) -> None:
        self._check(now_s)

    def _check(self, now_s: float) -> None:
        if self.engine is None:
            return
        for i, (point, action) in enumerate(self.actions):
            if i not in (f for f, _ in self.fired) and point(self.engine, self):
                self.fired.append((i, now_s))
                action()


def power_loss(points: RunPoints, accel_bias_step_m_s2: np.ndarray, down_s: float = 3.0) -> Callable[[], None]:
    """An action for :class:`RunPoints` on the in-process emulator: the IMU loses power now
    (its ``imu_power`` fault) for ``down_s`` virtual s and comes back with its accelerometer bias
    moved by ``accel_bias_step_m_s2`` (3,), m/s^2: a new turn-on bias. The emulator draws one of
    its own too (the config's turn-on repeatability), added to this step: a config with
    ``helpers.NO_TURN_ON_DRAW`` makes the step exactly this one."""
    def act() -> None:
        world = points.engine.rig.imu.world
        world.faults.schedule("imu_power", world.t, down_s)
        model = world.imu_model

        def back() -> None:
            model.accel_bias = model.accel_bias + np.asarray(accel_bias_step_m_s2, float)
        world.faults.call_at(world.t + down_s, back)
    return act


def point_options(points: RunPoints) -> RunOptions:
    """Run options of an in-process run watched by ``points``: 1 s hold of the suspenders, no
    free-space floor."""
    from rigctl.config.suspenders import SuspenderSettings
    return RunOptions(suspenders=SuspenderSettings(hold_s=1.0, min_free_bytes=0), progress=points,
                      on_engine=points.on_engine)


def pull(name: str, down_s: float = 0.05) -> Callable[[Any], None]:
    """An action for :func:`wired_run`: pull the cable of pty ``name`` for ``down_s`` wall s, then
    plug a new pty in at the same symlink. The cable is pulled in the engine's thread, so that the
    port is gone before the engine's next poll, whatever the host's scheduling; the outage runs
    in the background. (Held in the engine's thread, the outage put the next poll 5 s of rig
    time later at 100x: past the end of a 3 s window pulled 1 s into it, where a trip no longer
    cuts off a window its samples cover, rigctl.engine.engine.Engine.execute.)"""
    def act(hw) -> None:
        hw.disconnect(name, down_s, block=False)
    return act


def wired_run(tmp: Path, proc: str | Path, params: dict[str, str], table: str, link: str, speed: float,
              at: list[tuple[RunPoint, Callable[[Any], Any]]] | None = None, hw_kw: dict | None = None,
              suspenders: dict | None = None):
    """Run ``proc`` (in procedures/, or a path) over the wire against fresh emulated hardware
    (``hw_kw``: e.g. imu_protocol="vectornav"; ``suspenders``: the config's section; ``at``:
    (point of the run, action on the hardware) -- e.g. :func:`pull` -- done when the run reaches
    that point, :class:`RunPoints`); returns (recording, truth, hw info; info["fired"]: the rig
    times at which the actions were done, in the order of ``at``, None for those not done)."""
    with hardware(tmp, speed, **(hw_kw or {})) as (hw, raw):
        cfg_path = write_wire_config(tmp / "wired.yaml", raw, hw, table=table, link=link)
        if suspenders is not None:
            d = yaml.safe_load(cfg_path.read_text())
            d["suspenders"] = suspenders
            cfg_path.write_text(yaml.safe_dump(d, sort_keys=False))
        points = RunPoints([(point, lambda act=act: act(hw)) for point, act in (at or [])])
        t0 = time.perf_counter()
        res, cfg = run(proc, cfg_path, tmp / "runs", params,
                       RunOptions(progress=points, on_engine=points.on_engine) if at else None)
        info = {"wall_s": time.perf_counter() - t0, "truth": hw.truth(), "hw": hw,
                "imu_overflow": hw.slots["imu"].endpoint.overflow_bytes, "imu_frames_sent": hw.imu_server.frames_sent,
                "fired": [dict(points.fired).get(i) for i in range(len(at or []))],
                "reconnects": {k: s.reconnects for k, s in hw.slots.items()}}
    return res.recording, cfg, info


def segments(path: Path) -> dict[str, np.ndarray]:
    with h5py.File(path, "r") as f:
        return {k: f["segments"][k][()] for k in f["segments"]}


def window_means(path: Path, seg: dict[str, np.ndarray], kind: bytes, field: str) -> list[np.ndarray]:
    with h5py.File(path, "r") as f:
        data = f[f"imu/{field}"]
        return [data[int(a):int(z)].mean(axis=0) for k, a, z in
                zip(seg["kind"], seg["first_sample"], seg["last_sample"]) if k == kind]


def repeated_samples(path: Path) -> list[tuple[int, int]]:
    """(first row, number of rows) of every run of consecutive recorded IMU samples that are
    identical in all six channels. On a noisy IMU two consecutive samples are never alike (white
    noise of 5e-3 m/s^2 per sample against float32 steps of 1e-6 at 1 g), so any run is a sample
    the emulator or the recorder repeated (such runs biased 5 s window means by up to 9 sigma
    before the tap fix of tests/test_hil_tap.py)."""
    with h5py.File(path, "r") as f:
        x = np.hstack([f["imu/specific_force"][()], f["imu/angular_rate"][()]])
    same = np.concatenate([[False], np.all(x[1:] == x[:-1], axis=1), [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(same))
    return [(int(a) - 1, int(b - a) + 1) for a, b in zip(edges[::2], edges[1::2])]


# -- unattended operation over the wire (tests/test_daemon_wire*.py) -------------------------------
def write_wired(tmp: Path, raw: dict, hw, *, table: str = "acl", link: str = "pty", pulses: str = "novatel",
                suspenders: dict | None = None, imu: dict | None = None, name: str = "wired.yaml") -> Path:
    """A wired rig config for ``hw`` (NovAtel pulses by default), with an optional
    ``suspenders:`` section and extra ``imu`` keys (e.g. link_timeout_s)."""
    path = write_wire_config(tmp / name, raw, hw, table=table, link=link, pulses=pulses)
    d = yaml.safe_load(path.read_text())
    if suspenders is not None:
        d["suspenders"] = suspenders
    d["imu"].update(imu or {})
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path


@contextmanager
def wired(tmp: Path, speed: float, *, hw_kw: dict | None = None, **cfg_kw: Any):
    """Emulated hardware in this process (its own threads) and a wired config for it:
    yields (hw, config path)."""
    with hardware(tmp, speed, **(hw_kw or {})) as (hw, raw):
        yield hw, write_wired(tmp, raw, hw, **cfg_kw)


def table_snapshot(hw) -> dict[str, Any]:
    """The emulated controller's own view: per axis mode, rate (deg/s) and status word."""
    reads = [hw.table.read(a) for a in (1, 2, 3)]
    return {"mode": [hw.table.get_mode(a) for a in (1, 2, 3)],
            "rate_dps": [float(np.degrees(r["rate"])) for r in reads],
            "status": [int(r["status"]) for r in reads]}


def wait_until(pred, timeout: float, what: str, poll: float = 0.005):
    """Poll ``pred()`` until it returns something truthy; AssertionError naming ``what`` after
    ``timeout`` wall seconds."""
    end = time.monotonic() + timeout
    while True:
        v = pred()
        if v:
            return v
        if time.monotonic() > end:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(poll)


def wait_progress(pred, progress, what: str, stall_s: float = 30.0, poll: float = 0.01):
    """Poll ``pred()`` until it returns something truthy, as long as ``progress()`` (a count
    that grows while the work goes on: frames sent, frames decoded, rig seconds computed) keeps
    changing; AssertionError naming ``what`` once it has not changed for ``stall_s`` wall
    seconds. A deadline that scales with the machine's speed: a loaded machine gets there
    later, a stuck one still fails."""
    last, since = progress(), time.monotonic()
    while True:
        v = pred()
        if v:
            return v
        now = progress()
        if now != last:
            last, since = now, time.monotonic()
        elif time.monotonic() - since > stall_s:
            raise AssertionError(f"no progress for {stall_s:g} s waiting for {what} (at {last})")
        time.sleep(poll)


def affordable_speed(cfg, tmp: Path, want: float, **kw: Any) -> float:
    """The speed (x real time, at most ``want``) at which the emulator's physics for ``cfg``
    keeps up on this machine now: throwaway hardware at ``want`` (``kw``: start_hardware's) is
    timed over 1 s of wall time after its first chunk; 70 % of the rig seconds it computed per
    wall second, or ``want`` when it kept up. A test that needs the stream to flow picks its speed
    with it (on an idle machine ``want``; under load lower, so the test takes longer instead of
    starving its stream)."""
    with start_hardware(cfg, want, link_dir=tmp / "probe-ports", **kw) as hw:
        wait_progress(lambda: hw.table._t() > 0, lambda: 0, "the emulator's first physics chunk", 60.0)
        t0, w0 = time.monotonic(), hw.table._t()
        time.sleep(1.0)
        rate = (hw.table._t() - w0) / (time.monotonic() - t0)
    return want if rate >= 0.9 * want else max(1.0, 0.7 * rate)


def commands_since(hw, t0: float) -> list[tuple[float, str]]:
    """ACL request lines the emulated controller received since wall time ``t0``."""
    return [(t, line) for t, line in list(hw.acl.core.received) if t >= t0]


def sent_time_of(hw, row: np.ndarray) -> float | None:
    """Wall time at which the emulator wrote the IMU frame whose accelerometer values are
    ``row`` (3 floats as recorded; compared as the float32 values on the wire), or None when it
    is not among the batches it still keeps (``imu_keep_sent``)."""
    want = np.asarray(row, dtype=np.float32)
    for wall, _t, acc, _whole in reversed(list(hw.xsens.sent)):
        if (acc == want).all(axis=1).any():
            return wall
    return None
