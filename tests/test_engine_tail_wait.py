"""A suspender that trips after a sampling window, while the engine waits for the window's last
samples still in flight (Engine._window_rows): the window's own samples decide.

* they cover the window: the step is complete, the run pauses before the next step; a warm-up
  is not started over -- the IMU streamed to its end, whatever the link did after;
* they stop inside it (a link loss that took the samples in flight with it): as a trip while
  sampling -- the step is sampled again, a warm-up starts over (the IMU may have lost power).

Before, any trip there cut the step off: a link drop after a complete 20 s warm-up ran the whole
warm-up again, and an operator pause there credited the warm-up with more than its length (the
wait's time counted as warm-up), so it re-ran as a 0 s window that came out short.

The in-process emulator on the virtual clock (deterministic), its IMU behind a link with a
latency (samples arrive ``lag_s`` of rig time after their time stamps; a link loss loses those
in flight), the loss injected with the emulator's ``imu_link`` fault at the first poll after
the warm-up's window.
"""
from __future__ import annotations

import io
import multiprocessing
import os
import signal
from contextlib import contextmanager

import h5py
import numpy as np

from rigctl.config.config import load_config
from rigctl.config.suspenders import SuspenderSettings
from rigctl.devices import ImuBlock, LinkLost
from rigctl.engine.procedure import load_procedure
from rigctl.engine.rig import open_rig
from rigctl.run.runner import RunOptions, resume_run, run_procedure

from helpers import WHITE_NOISE_ONLY, derived_config

RATE_HZ = 100.0
WARMUP_S = 20.0
PROC = """procedure: tail-wait
steps:
  - warmup:
      duration: 20 s
  - orientations:
      angles_deg: [[0, 0, 0], [90, 0, 0]]
      sample: 5 s
      discard: 1 s
      settle: {hold: 1 s, timeout: 60 s}
"""
FIELDS = ("time", "counter", "specific_force", "angular_rate", "temperature")


class LinkWithLatency:
    """The emulated IMU behind a link delivering each sample ``lag_s`` of rig time after its
    stamp; a link loss (the emulator's ``imu_link`` fault) loses the samples in flight. At the
    first read after the warm-up's window has ended, ``act(engine, world, now)`` runs once;
    ``on_read(engine)`` at every read."""

    def __init__(self, inner, clock, lag_s: float, act, on_read=None) -> None:
        self.inner, self.clock, self.lag_s, self.act, self.on_read = inner, clock, lag_s, act, on_read
        self.identity = getattr(inner, "identity", {})
        self.engine = None
        self.acted_at: float | None = None
        self._held: list[ImuBlock] = []

    def read(self) -> ImuBlock:
        e, now = self.engine, self.clock.now()
        if self.on_read is not None and e is not None:
            self.on_read(e)
        step = e.current_step if e is not None else None
        if (self.acted_at is None and step is not None and step.kind == "warmup" and e._win_start is not None
                and now > e._win_start + step.sample_s + 1e-6):
            self.acted_at = now
            self.act(e, self.inner.world, now)
        try:
            b = self.inner.read()
        except LinkLost:
            self._held = []           # the samples in flight go with the link
            raise
        if len(b):
            self._held.append(b)
        if not self._held:
            return ImuBlock.empty()
        cols = [np.concatenate([getattr(h, k) for h in self._held]) for k in FIELDS]
        cut = int(np.searchsorted(cols[0], now - self.lag_s, side="right"))
        rest = ImuBlock(*(c[cut:] for c in cols))
        self._held = [rest] if len(rest) else []
        return ImuBlock(*(c[:cut] for c in cols))


def link_loss(down_s: float):
    def act(engine, world, now):
        world.faults.schedule("imu_link", now, down_s)
    return act


def operator_pause(engine, world, now):
    engine.request_pause("paused by operator")
    world.faults.call_at(now + 3.0, engine.request_resume)


def _run(tmp_path, lag_s: float, act, on_read=None, proc_text: str = PROC):
    cfg = load_config(derived_config(tmp_path, **WHITE_NOISE_ONLY))     # virtual clock, 100 Hz
    assert cfg.imu_rate_hz == RATE_HZ
    (tmp_path / "proc.yaml").write_text(proc_text)
    proc = load_procedure(tmp_path / "proc.yaml", limits=cfg.limits)
    links: list[LinkWithLatency] = []

    @contextmanager
    def opener(c):
        with open_rig(c) as (rig, truth):
            rig.imu = LinkWithLatency(rig.imu, rig.clock, lag_s, act, on_read)
            links.append(rig.imu)
            yield rig, truth

    def on_engine(engine):
        if engine is not None and links:
            links[-1].engine = engine

    opts = RunOptions(suspenders=SuspenderSettings(hold_s=1.0, min_free_bytes=0), rig_opener=opener,
                      on_engine=on_engine)
    res = run_procedure(proc, cfg, tmp_path / "runs", console=io.StringIO(), install_signals=False, options=opts)
    assert links[0].acted_at is not None, "the warm-up's window never ended"
    return res, links[0].acted_at


def _read(path):
    with h5py.File(path, "r") as f:
        seg = {k: f["segments"][k][()] for k in ("kind", "status", "step", "first_sample", "last_sample",
                                                  "t_start", "t_end")}
        t = f["imu/time"][()]
        c = f["imu/counter"][()].astype(np.int64)
        events = [(float(tt), k.decode(), m.decode()) for tt, k, m in
                  zip(f["events/time"][()], f["events/kind"][()], f["events/message"][()])]
    return seg, t, c, events


def _whole(seg, t, c, i, want_s):
    """Segment i's rows are every sample stamped inside its window, on an unbroken counter, and
    they span it within two sample periods (checked here from the recorded rows)."""
    a, z = int(seg["first_sample"][i]), int(seg["last_sample"][i])
    inside = np.flatnonzero((t >= seg["t_start"][i] - 1e-6) & (t < seg["t_end"][i] - 1e-6))
    assert (a, z) == (int(inside[0]), int(inside[-1]) + 1)
    assert np.all(np.diff(c[a:z]) == 1)
    assert abs((seg["t_end"][i] - seg["t_start"][i]) - want_s) < 1e-6
    assert t[z - 1] - t[a] + 1 / RATE_HZ >= want_s - 2 / RATE_HZ - 1e-9


def test_a_link_loss_after_a_whole_warmup_pauses_before_the_next_step(tmp_path):
    """Latency 15 ms (1.5 periods): the warm-up's samples all but the last one or two have
    arrived when the link drops for 3 s, right after its window. The warm-up is complete as
    recorded (one segment, not run again: before, it was cut off and ran a second time); the run
    pauses on 'imu-link' before the first orientation and goes on."""
    res, acted = _run(tmp_path, 0.015, link_loss(3.0))
    assert res.exit_code == 0, res.message
    seg, t, c, events = _read(res.recording)
    kinds = [k.decode() for k in seg["kind"]]
    assert kinds == ["warmup", "orientation", "orientation"], kinds
    assert all(s == b"complete" for s in seg["status"])
    _whole(seg, t, c, 0, WARMUP_S)
    # the pause: after the warm-up's window, before the first orientation's, on the link loss
    # (the counter gap at the reconnect is noted while paused: 'also')
    sus = [(tt, m) for tt, k, m in events if k == "suspend"]
    assert sus[0][1].startswith("imu-link:") and all(m.startswith(("imu-link:", "imu-gap:")) for _, m in sus), sus
    assert seg["t_end"][0] <= acted <= sus[0][0] and sus[-1][0] < seg["t_start"][1]
    assert [k for _, k, _ in events].count("resume") == 1
    assert any(k == "info" and "tripped after its window" in m and "the step is complete" in m
               for _, k, m in events), events
    assert not any(k == "incomplete" for _, k, m in events)
    # the samples lost with the link lie between the two steps: a counter gap of about 3 s
    gap = np.flatnonzero(np.diff(c) > 1)
    assert len(gap) == 1 and seg["last_sample"][0] <= gap[0] + 1 <= seg["first_sample"][1]
    assert 250 <= c[gap[0] + 1] - c[gap[0]] - 1 <= 400


def test_a_link_loss_that_takes_the_last_samples_restarts_the_warmup(tmp_path):
    """Latency 0.5 s: the link drop after the window takes 50 of the warm-up's samples with it,
    so its data stop inside it -- as a drop while sampling: the warm-up starts over (the IMU may
    have been without power for its last half second) and is recorded whole the second time."""
    res, acted = _run(tmp_path, 0.5, link_loss(3.0))
    assert res.exit_code == 0, res.message
    seg, t, c, events = _read(res.recording)
    pairs = [(k.decode(), s.decode()) for k, s in zip(seg["kind"], seg["status"])]
    assert pairs == [("warmup", "incomplete"), ("warmup", "complete"), ("orientation", "complete"),
                     ("orientation", "complete")], pairs
    _whole(seg, t, c, 1, WARMUP_S)        # the whole 20 s again, not what was left
    # the first attempt's samples end half a second (the latency) before the window did
    last = t[int(seg["last_sample"][0]) - 1]
    assert acted - 0.5 - 0.05 - 1 / RATE_HZ - 1e-6 <= last <= acted - 0.5, (last, acted)


def test_an_operator_pause_after_the_window_keeps_the_warmup(tmp_path):
    """An operator pause requested right after the warm-up's window, with 0.5 s of samples still
    in flight: the wait goes on for them, the warm-up is complete, the pause comes before the
    first orientation. Before: the warm-up was cut off and credited with the wait's time too
    (more than its 20 s), re-ran as a 0 s window that came out short, and then started over."""
    res, acted = _run(tmp_path, 0.5, operator_pause)
    assert res.exit_code == 0, res.message
    seg, t, c, events = _read(res.recording)
    kinds = [k.decode() for k in seg["kind"]]
    assert kinds == ["warmup", "orientation", "orientation"] and all(s == b"complete" for s in seg["status"])
    _whole(seg, t, c, 0, WARMUP_S)
    sus = [(tt, m) for tt, k, m in events if k == "suspend"]
    assert len(sus) == 1 and sus[0][1].startswith("operator:") and sus[0][0] < seg["t_start"][1], sus
    assert not any(k == "short-window" for _, k, m in events)


def _crash_when_paused(tmp_path):
    """Child process: the run of the first test with a link that stays down; SIGKILL at the
    first poll once the run is paused."""
    def act(engine, world, now):
        world.faults.schedule("imu_link", now, np.inf)

    def crash(engine):
        if engine.states.state == "paused":
            os.kill(os.getpid(), signal.SIGKILL)
    _run(tmp_path, 0.015, act, on_read=crash)
    os._exit(3)     # not reached: the run never resumes


def test_a_run_killed_while_paused_there_resumes_after_the_warmup(tmp_path):
    """The link stays down after the whole warm-up and the process is killed (SIGKILL) while the
    run is paused before the first orientation: 'rigctl resume' goes on with the orientations --
    the warm-up is complete in the recording and does not run again."""
    child = multiprocessing.get_context("fork").Process(target=_crash_when_paused, args=(tmp_path,))
    child.start()
    child.join(60)
    assert child.exitcode == -signal.SIGKILL, child.exitcode
    (run_dir,) = (tmp_path / "runs").iterdir()
    again = resume_run(run_dir, tmp_path / "runs", console=io.StringIO(), install_signals=False)
    assert again.status == "complete", again.message
    seg, t, c, events = _read(again.recording)
    pairs = [(k.decode(), s.decode()) for k, s in zip(seg["kind"], seg["status"])]
    assert pairs == [("warmup", "complete"), ("orientation", "complete"), ("orientation", "complete")], pairs
    _whole(seg, t, c, 0, WARMUP_S)


def test_a_link_loss_after_the_last_window_completes_the_run(tmp_path):
    """The same link loss after the window of a run's last step: nothing is left to pause for;
    the run completes with the step, and its log says what tripped."""
    res, _ = _run(tmp_path, 0.015, link_loss(3.0), proc_text=PROC.split("  - orientations:")[0])
    assert res.exit_code == 0 and res.status == "complete", res.message
    seg, t, c, events = _read(res.recording)
    assert [(k, s) for k, s in zip(seg["kind"], seg["status"])] == [(b"warmup", b"complete")]
    _whole(seg, t, c, 0, WARMUP_S)
    assert not any(k in ("suspend", "incomplete") for _, k, _ in events), events
    log = (res.run_dir / "run.log.jsonl").read_text()
    assert "imu-link after the last window: IMU link lost" in log and "every step is complete" in log


def _pause_names(events) -> list[set[str]]:
    """Per pause (a suspend to its resume), the suspenders its suspend events name, with the
    names its resume says are clear: (suspend names, resume names)."""
    out, cur = [], None
    for _, k, m in events:
        if k == "suspend":
            cur = set() if cur is None else cur
            cur |= set(m.split(": ", 1)[0].split(", "))
        elif k == "resume":
            assert cur is not None, m
            out.append((cur, set(m.split(" clear for ", 1)[0].split(", "))))
            cur = None
    return out


def test_a_trip_later_in_the_tail_wait_is_recorded_in_the_pause(tmp_path):
    """The link drops for 0.3 s right after the warm-up's window (latency 15 ms): 'imu-link'
    trips in the wait for its last samples, and the samples that follow the reconnect carry a
    counter gap: 'imu-gap' trips in a later poll of the same wait. The pause names both (in its
    suspend events and its resume). Before, polls after the first trip of the wait did not check
    the suspenders: the gap was in no event."""
    res, acted = _run(tmp_path, 0.015, link_loss(0.3))
    assert res.exit_code == 0, res.message
    seg, t, c, events = _read(res.recording)
    gap = np.flatnonzero(np.diff(c) > 1)
    assert len(gap) == 1 and 20 <= c[gap[0] + 1] - c[gap[0]] - 1 <= 40       # the 0.3 s outage
    assert acted <= t[gap[0] + 1] <= acted + 2.0                              # inside the tail wait
    pauses = _pause_names(events)
    assert len(pauses) == 1 and pauses[0][0] == pauses[0][1] == {"imu-link", "imu-gap"}, events
    named = [m for _, k, m in events if k == "suspend" and f"(counter {c[gap[0]]} -> {c[gap[0] + 1]})" in m]
    assert len(named) == 1 and "imu-gap" in named[0], events


def test_a_trip_while_the_table_stops_is_recorded_in_the_pause(tmp_path):
    """An operator pause right after the warm-up's window; at the poll that stops the table
    (the run 'pausing') the link drops for 0.1 s, shorter than a pause poll, so 'imu-link' is
    clear again at the pause's first poll. The pause names it (a suspend event, and its resume).
    Before, the table-stop polls did not record trips: the pause named 'operator' and the
    'imu-gap' of the reconnect only, not the link loss."""
    dropped: list[float] = []

    def drop_while_stopping(engine):
        if engine.states.state == "pausing" and not dropped:
            now = engine.rig.clock.now()
            dropped.append(now)
            engine.rig.imu.inner.world.faults.schedule("imu_link", now, 0.1)

    res, _ = _run(tmp_path, 0.015, operator_pause, on_read=drop_while_stopping)
    assert res.exit_code == 0, res.message
    assert dropped
    seg, t, c, events = _read(res.recording)
    pauses = _pause_names(events)
    assert len(pauses) == 1 and pauses[0][0] == pauses[0][1], events
    assert {"operator", "imu-link"} <= pauses[0][0], events
    link = [(tt, m) for tt, k, m in events if k == "suspend" and m.startswith("imu-link")]
    assert len(link) == 1 and "link down, injected" in link[0][1] and link[0][0] >= dropped[0], events


def test_a_suspender_that_trips_again_in_a_pause_is_recorded_again(tmp_path):
    """An operator pause right after the warm-up's window; once paused, the link drops twice for
    0.3 s, 1 s apart: 'imu-link' trips, clears, trips again, and each reconnect leaves its own
    counter gap ('imu-gap' twice). Each trip is a suspend event, each gap named by its counters.
    Before, a suspender the pause already named got no event when it tripped again: the second
    link loss and the second gap's counters were in no event."""
    drops: list[float] = []

    def drop_twice_when_paused(engine):
        if engine.states.state == "paused" and not drops:
            now = engine.rig.clock.now()
            drops.extend([now + 0.2, now + 1.2])
            for t in drops:
                engine.rig.imu.inner.world.faults.schedule("imu_link", t, 0.3)

    res, _ = _run(tmp_path, 0.015, operator_pause, on_read=drop_twice_when_paused)
    assert res.exit_code == 0, res.message
    assert drops
    seg, t, c, events = _read(res.recording)
    gaps = np.flatnonzero(np.diff(c) > 1)
    assert len(gaps) == 2 and all(20 <= c[g + 1] - c[g] - 1 <= 40 for g in gaps), c[gaps]   # 0.3 s each
    pauses = _pause_names(events)
    assert len(pauses) == 1 and pauses[0][0] == pauses[0][1] == {"operator", "imu-link", "imu-gap"}, events
    link = [tt for tt, k, m in events if k == "suspend" and m.startswith("imu-link")]
    assert len(link) == 2 and drops[0] <= link[0] < drops[1] <= link[1], (drops, events)
    for g in gaps:
        named = [m for _, k, m in events if k == "suspend" and f"(counter {c[g]} -> {c[g + 1]})" in m]
        assert len(named) == 1 and "imu-gap" in named[0], (c[g], c[g + 1], events)
