"""An IMU that restarts mid-procedure (it lost power: its device time began again) is warmed up
again before the next measurement; a plain link drop (device time continuous) is not.

The in-process emulator on the virtual clock (deterministic, seconds): its ``imu_power`` fault
takes the link down and, when it ends, restarts the unit (``counters["device_restarts"]``, as
drivers/stream_imu.py counts a rebased timeline); ``imu_link`` is the cable pull. The faults are
injected 1 s into the second orientation's window. The wire path (pty, Xsens driver, emulated
power cycle) is tests/test_hil_power_cycle.py.

Before: a restart after the warm-up never re-warmed the IMU (only a warm-up in flight started
over), and the recording did not say where it happened.
"""
from __future__ import annotations

import io
import multiprocessing
import os
import signal

import h5py
import numpy as np

from rigctl.config.config import load_config
from rigctl.config.suspenders import SuspenderSettings
from rigctl.engine.procedure import load_procedure
from rigctl.run.runner import RunOptions, resume_run, run_procedure

from helpers import NO_TURN_ON_DRAW, WHITE_NOISE_ONLY, derived_config
from hil_support import RunPoints, sampling

WARMUP_S = 20.0
PROC = """procedure: rewarm
steps:
  - warmup:
      duration: 20 s
  - orientations:
      angles_deg: [[0, 0, 0], [90, 0, 0], [180, 0, 0]]
      sample: 5 s
      discard: 1 s
      settle: {hold: 1 s, timeout: 60 s}
"""


def _run(tmp_path, fault: str, down_s: float = 3.0, on_poll=None, at=None):
    cfg = load_config(derived_config(tmp_path, **WHITE_NOISE_ONLY))     # virtual clock, 100 Hz
    (tmp_path / "proc.yaml").write_text(PROC)
    proc = load_procedure(tmp_path / "proc.yaml", limits=cfg.limits)
    points: RunPoints

    def inject() -> None:
        world = points.engine.rig.imu.world
        world.faults.schedule(fault, world.t, down_s)

    points = RunPoints([(at or sampling("orientation", after_samples=100, finished=1), inject)])
    if on_poll is not None:
        points.actions.append((lambda engine, pts: on_poll(engine), lambda: None))
    opts = RunOptions(suspenders=SuspenderSettings(hold_s=1.0, min_free_bytes=0), progress=points,
                      on_engine=points.on_engine)
    res = run_procedure(proc, cfg, tmp_path / "runs", console=io.StringIO(), install_signals=False, options=opts)
    assert points.fired, "the fault was never injected"
    return res


def _read(path):
    with h5py.File(path, "r") as f:
        seg = {k: f["segments"][k][()] for k in ("kind", "status", "step", "first_sample", "last_sample",
                                                  "t_start", "t_end")}
        t = f["imu/time"][()]
        events = [(float(tt), k.decode(), m.decode()) for tt, k, m in
                  zip(f["events/time"][()], f["events/kind"][()], f["events/message"][()])]
    return seg, t, events


def _pairs(seg):
    return [(k.decode(), int(i), s.decode()) for k, i, s in zip(seg["kind"], seg["step"], seg["status"])]


def test_a_power_loss_after_the_warmup_warms_the_imu_again(tmp_path):
    """Power lost for 3 s during the second orientation: a ``device-restart`` event naming the
    step and the last complete one; the orientation is cut off; the whole 20 s warm-up runs
    again (a complete warm-up segment, after the restart) before the orientation is sampled
    again; the run log says so in one line."""
    res = _run(tmp_path, "imu_power")
    assert res.exit_code == 0, res.message
    seg, t, events = _read(res.recording)
    assert _pairs(seg) == [("warmup", 0, "complete"), ("orientation", 1, "complete"),
                           ("orientation", 2, "incomplete"), ("warmup", 0, "complete"),
                           ("orientation", 2, "complete"), ("orientation", 3, "complete")], _pairs(seg)
    (restart,) = [(tt, m) for tt, k, m in events if k == "device-restart"]
    assert "in step 3 (" in restart[1] and "last complete step 2 (" in restart[1], restart
    # the re-warm starts after the restart, lasts the procedure's warm-up, and its samples cover it
    a, z = int(seg["first_sample"][3]), int(seg["last_sample"][3])
    assert seg["t_start"][3] >= restart[0]
    assert abs(seg["t_end"][3] - seg["t_start"][3] - WARMUP_S) < 1e-6
    assert abs((t[z - 1] - t[a] + 0.01) - WARMUP_S) <= 0.02 + 1e-9
    assert seg["t_end"][3] <= seg["t_start"][4]
    log = (res.run_dir / "run.log.jsonl").read_text().splitlines()
    said = [line for line in log if "the IMU restarted in step 3" in line]
    assert len(said) == 1 and "warm-up (20 s, step 1) runs again first, then step 3 is sampled again" in said[0], said


def test_a_link_drop_does_not_warm_the_imu_again(tmp_path):
    """The same 3 s outage as a cable pull (device time continuous): the orientation is sampled
    again, and no warm-up runs again."""
    res = _run(tmp_path, "imu_link")
    assert res.exit_code == 0, res.message
    seg, t, events = _read(res.recording)
    assert _pairs(seg) == [("warmup", 0, "complete"), ("orientation", 1, "complete"),
                           ("orientation", 2, "incomplete"), ("orientation", 2, "complete"),
                           ("orientation", 3, "complete")], _pairs(seg)
    assert not any(k == "device-restart" for _, k, _ in events)


def test_a_power_loss_during_the_warmup_runs_it_once_more_only(tmp_path):
    """Power lost 5 s into the warm-up: the warm-up starts over (whole), once -- it is the
    re-warm -- and the event is recorded; no second warm-up before the orientations."""
    res = _run(tmp_path, "imu_power", at=sampling("warmup", after_samples=500))
    assert res.exit_code == 0, res.message
    seg, t, events = _read(res.recording)
    assert _pairs(seg) == [("warmup", 0, "incomplete"), ("warmup", 0, "complete"), ("orientation", 1, "complete"),
                           ("orientation", 2, "complete"), ("orientation", 3, "complete")], _pairs(seg)
    (restart,) = [(tt, m) for tt, k, m in events if k == "device-restart"]
    assert "in step 1 (" in restart[1] and "no step complete yet" in restart[1], restart
    assert seg["t_start"][1] >= restart[0] and abs(seg["t_end"][1] - seg["t_start"][1] - WARMUP_S) < 1e-6


def test_warmup_time_kept_before_a_restart_does_not_shorten_the_rewarm(tmp_path):
    """An IMU temperature excursion 5 s into the warm-up pauses it and keeps its 5 s (the
    warm-up then samples the 15 s left); a power loss later, in the second orientation: the
    re-warm is the whole 20 s, not 20 s less the time kept before the restart."""
    cfg = load_config(derived_config(tmp_path, **WHITE_NOISE_ONLY))
    (tmp_path / "proc.yaml").write_text(PROC)
    proc = load_procedure(tmp_path / "proc.yaml", limits=cfg.limits)
    points: RunPoints

    def fault(kind: str, **kw):
        def act() -> None:
            world = points.engine.rig.imu.world
            world.faults.schedule(kind, world.t, 3.0, **kw)
        return act

    points = RunPoints([(sampling("warmup", after_samples=500), fault("temperature", offset_c=200.0)),
                        (sampling("orientation", after_samples=100, finished=1), fault("imu_power"))])
    opts = RunOptions(suspenders=SuspenderSettings(hold_s=1.0, min_free_bytes=0), progress=points,
                      on_engine=points.on_engine)
    res = run_procedure(proc, cfg, tmp_path / "runs", console=io.StringIO(), install_signals=False, options=opts)
    assert res.exit_code == 0, res.message
    assert len(points.fired) == 2
    seg, t, events = _read(res.recording)
    pairs = _pairs(seg)
    warm = [i for i, p in enumerate(pairs) if p[0] == "warmup" and p[2] == "complete"]
    assert [p[0] for p in pairs[:2]] == ["warmup", "warmup"] and len(warm) == 2, pairs
    kept = seg["t_end"][warm[0]] - seg["t_start"][warm[0]]
    assert 14.0 < kept < 16.0, kept                        # the first warm-up kept its first 5 s
    (restart,) = [tt for tt, k, m in events if k == "device-restart"]
    assert seg["t_start"][warm[1]] >= restart
    assert abs(seg["t_end"][warm[1]] - seg["t_start"][warm[1]] - WARMUP_S) < 1e-6


def _crash_after_restart(tmp_path):
    """Child process: the power-loss run, SIGKILLed at the first poll after the engine saw the
    restart (paused, the re-warm not yet begun)."""
    def crash(engine):
        if getattr(engine, "rewarm", None) is not None:
            os.kill(os.getpid(), signal.SIGKILL)
        return False
    _run(tmp_path, "imu_power", on_poll=crash)
    os._exit(3)     # not reached


def test_a_run_killed_after_a_restart_warms_the_imu_again_on_resume(tmp_path):
    """Killed (SIGKILL) after the restart was recorded and before the re-warm: 'rigctl resume'
    runs the warm-up first (the recording says it is owed), then the orientations left."""
    child = multiprocessing.get_context("fork").Process(target=_crash_after_restart, args=(tmp_path,))
    child.start()
    child.join(60)
    assert child.exitcode == -signal.SIGKILL, child.exitcode
    (run_dir,) = (tmp_path / "runs").iterdir()
    again = resume_run(run_dir, tmp_path / "runs", console=io.StringIO(), install_signals=False)
    assert again.status == "complete", again.message
    seg, t, events = _read(again.recording)
    pairs = _pairs(seg)
    done = [p for p in pairs if p[2] == "complete"]
    assert done == [("warmup", 0, "complete"), ("orientation", 1, "complete"), ("warmup", 0, "complete"),
                    ("orientation", 2, "complete"), ("orientation", 3, "complete")], pairs
    (restart,) = [tt for tt, k, m in events if k == "device-restart"]
    i = [j for j, p in enumerate(pairs) if p[0] == "warmup"][1]
    assert seg["t_start"][i] > restart and abs(seg["t_end"][i] - seg["t_start"][i] - WARMUP_S) < 1e-6
    assert "resuming after a device restart" in (run_dir / "run.log.jsonl").read_text()


#: the bias the emulated unit comes back with after its power loss, on x (2 mg): a new turn-on bias
STEP_M_S2 = 2e-3 * 9.80665


def test_a_calibration_across_a_restart_names_the_positions_on_each_side(tmp_path):
    """procedures/24pos.yaml (3 s windows, 10 s warm-up) with the power lost 1 s into the 13th orientation,
    the unit back 3 s later with a 2 mg higher x bias: the run re-warms, and 'rigctl calibrate'
    says NOT TRUSTWORTHY, naming the 12 positions measured before the restart and the 12 after
    (from the segments' own times here): one fit over both has no term for the bias step."""
    from rigctl.analysis.calibration import calibrate
    from hil_support import ROOT
    cfg = load_config(derived_config(tmp_path, **WHITE_NOISE_ONLY, **NO_TURN_ON_DRAW))
    proc = load_procedure(ROOT / "procedures" / "24pos.yaml", {"warmup": "10 s", "sample": "3 s", "discard": "0.5 s"},
                          cfg.limits)
    from hil_support import point_options, power_loss
    points = RunPoints([])
    points.actions.append((sampling("orientation", after_samples=100, finished=12),
                           power_loss(points, np.array([STEP_M_S2, 0.0, 0.0]))))
    res = run_procedure(proc, cfg, tmp_path / "runs", console=io.StringIO(), install_signals=False,
                        options=point_options(points))
    assert res.exit_code == 0, res.message
    seg, t, events = _read(res.recording)
    (restart,) = [tt for tt, k, m in events if k == "device-restart"]
    done = (seg["kind"] == b"orientation") & (seg["status"] == b"complete")
    before = sorted(int(s) + 1 for s in seg["step"][done & (seg["t_end"] <= restart)])
    after = sorted(int(s) + 1 for s in seg["step"][done & (seg["t_start"] >= restart)])
    assert before == list(range(2, 14)) and after == list(range(14, 26)), (before, after)
    payload, text, _ = calibrate(res.recording, store=False)
    assert payload["trustworthy"] is False and payload["loop_status"] == "NOT TRUSTWORTHY"
    (note,) = payload["device_restarts"]
    assert [int(s.split(" ")[1]) for s in note["before"]] == before
    assert [int(s.split(" ")[1]) for s in note["after"]] == after
    assert "STATUS: NOT TRUSTWORTHY: IMU restarted at t = " in text
    assert "step 2 (" in text and "step 25 (" in text and "(12 positions)" in text


def test_a_restart_in_the_end_of_run_safe_state_is_logged_without_a_rewarm(tmp_path):
    """The unit restarts after the last step, noticed by the end-of-run safe state's poll: the
    ``device-restart`` event and one run-log line say so, and neither promises a warm-up that
    will never run (before: 'the warm-up (20 s, step 1) runs again first, then ...' although the
    run was over). Nothing is re-measured; the run completes."""
    cfg = load_config(derived_config(tmp_path, **WHITE_NOISE_ONLY))
    (tmp_path / "proc.yaml").write_text(PROC)
    proc = load_procedure(tmp_path / "proc.yaml", limits=cfg.limits)
    last = max(s.index for s in proc.steps if s.is_motion)

    class AtTheEnd(RunPoints):
        def step_finished(self, step, segment=None):
            super().step_finished(step, segment)
            if step.index == last:       # the power is lost and back before the safe state's poll
                self.engine.rig.imu.power_cycle()
    points = AtTheEnd([])
    opts = RunOptions(suspenders=SuspenderSettings(hold_s=1.0, min_free_bytes=0), progress=points,
                      on_engine=points.on_engine)
    res = run_procedure(proc, cfg, tmp_path / "runs", console=io.StringIO(), install_signals=False, options=opts)
    assert res.exit_code == 0 and res.status == "complete", res.message
    assert points.engine.rig.imu.device_restarts == 1
    seg, t, events = _read(res.recording)
    assert _pairs(seg) == [("warmup", 0, "complete"), ("orientation", 1, "complete"),
                           ("orientation", 2, "complete"), ("orientation", 3, "complete")], _pairs(seg)
    (restart,) = [(tt, m) for tt, k, m in events if k == "device-restart"]
    assert restart[0] >= seg["t_end"][-1] and "end-of-run safe state" in restart[1], restart
    assert "re-run" not in restart[1] and "warm-up" not in restart[1], restart
    log = (res.run_dir / "run.log.jsonl").read_text().splitlines()
    said = [line for line in log if "the IMU restarted" in line]
    assert len(said) == 1 and "end-of-run safe state" in said[0], said
    assert not any("runs again" in line for line in log), [x for x in log if "runs again" in x]
    assert points.engine.rewarm is None


def after_window(kind: str, finished: int = 0):
    """The poll that ends a ``kind`` step's sampling window (the clock at its end), once
    ``finished`` segments of that kind have been finished: the engine then awaits the window's
    last samples (Engine._window_rows), the step not yet recorded."""
    def at(engine, points) -> bool:
        step = engine.current_step
        return (points.starting is None and step is not None and step.kind == kind
                and engine._win_start is not None and engine.rig.clock.now() >= engine._win_start + step.sample_s - 1e-9
                and sum(1 for s in points.done if s.kind == kind) >= finished)
    return at


def _power_loss_run(tmp_path, at, down_s: float, lag_s: float = 0.0, more=(), proc_text: str = PROC,
                    cfg_extra=None, also=(), complete: bool = True):
    """PROC with the IMU's power lost for ``down_s`` at point ``at`` (hil_support.power_loss, a
    2 mg x bias step, no turn-on draw of the emulator's own) and at the points of ``more``,
    ((point, down_s), ...); returns the result, the points, the segments, the IMU times, the
    ``device-restart`` events (time, message) and the run-log lines saying a restart (one per
    restart; a single restart: that one event and line); ``lag_s`` > 0: the IMU behind a
    link delivering each sample that long after its stamp (test_engine_tail_wait.LinkWithLatency,
    its restart count passed through), so the engine awaits a window's last samples after it.
    ``proc_text`` instead of PROC, ``cfg_extra`` more config (a chamber), ``also`` more
    (point, make) pairs (the action: make(points)); ``complete`` False: the run need not
    complete."""
    from contextlib import contextmanager

    from hil_support import point_options, power_loss
    from rigctl.engine.rig import open_rig
    from test_engine_tail_wait import LinkWithLatency

    class Lagging(LinkWithLatency):
        @property
        def world(self):
            return self.inner.world

        @property
        def device_restarts(self) -> int:
            return self.inner.device_restarts

    cfg = load_config(derived_config(tmp_path, **WHITE_NOISE_ONLY, **NO_TURN_ON_DRAW, **(cfg_extra or {})))
    (tmp_path / "proc.yaml").write_text(proc_text)
    proc = load_procedure(tmp_path / "proc.yaml", limits=cfg.limits)
    points = RunPoints([])
    for point, down in ((at, down_s), *more):
        points.actions.append((point, power_loss(points, np.array([STEP_M_S2, 0.0, 0.0]), down_s=down)))
    points.actions.extend((point, make(points)) for point, make in also)
    opts = point_options(points)
    if lag_s > 0.0:
        @contextmanager
        def opener(c):
            with open_rig(c) as (rig, truth):
                rig.imu = Lagging(rig.imu, rig.clock, lag_s, act=lambda *a: None)
                yield rig, truth
        opts.rig_opener = opener
    res = run_procedure(proc, cfg, tmp_path / "runs", console=io.StringIO(), install_signals=False, options=opts)
    assert len(points.fired) == 1 + len(more) + len(also), "a power loss (or an action) never fired"
    imu = points.engine.rig.imu
    assert getattr(imu, "inner", imu).device_restarts == 1 + len(more)
    assert not complete or (res.exit_code == 0 and res.status == "complete"), res.message
    seg, t, events = _read(res.recording)
    restarts = [(tt, m) for tt, k, m in events if k == "device-restart"]
    said = [line for line in (res.run_dir / "run.log.jsonl").read_text().splitlines() if "the IMU restarted" in line]
    assert len(restarts) == len(said) == 1 + len(more), (restarts, said)
    if more:
        return res, points, seg, t, restarts, said
    return res, points, seg, t, restarts[0], said[0]


def test_a_restart_after_a_complete_window_rewarms_before_the_next_step_and_says_so(tmp_path):
    """The power lost for 0.5 s as the second orientation's window ends: the restart is noticed
    while the engine awaits the window's last samples, which cover it (those before the loss).
    Step 3 is complete and not sampled again: the event and the run log say the restart came
    after its window, before step 4, and that the warm-up runs again first, then step 4 (before:
    'in step 3 ...', 'then step 3 is sampled again'). The re-warm (20 s) starts after the restart
    and precedes step 4."""
    res, points, seg, t, restart, said = _power_loss_run(tmp_path, after_window("orientation", finished=1), 0.5, lag_s=0.015)
    assert _pairs(seg) == [("warmup", 0, "complete"), ("orientation", 1, "complete"),
                           ("orientation", 2, "complete"), ("warmup", 0, "complete"),
                           ("orientation", 3, "complete")], _pairs(seg)
    assert seg["t_end"][2] <= restart[0] <= seg["t_start"][3], (restart, seg["t_end"][2], seg["t_start"][3])
    assert abs(seg["t_end"][3] - seg["t_start"][3] - WARMUP_S) < 1e-6
    assert "after step 3's window, before step 4;" in restart[1], restart
    assert "last complete step 3 (" in restart[1] and "warm-up re-runs (20 s)" in restart[1], restart
    assert "sampled again" not in said and "the warm-up (20 s, step 1) runs again first, then step 4 runs" in said, said
    assert points.engine.rewarm is None


def test_a_restart_after_the_last_window_promises_no_rewarm(tmp_path):
    """The same 0.5 s power loss as the last orientation's window ends: every step is complete and
    nothing more is sampled. The event and the run log say no step runs after it (as in the
    end-of-run safe state), no warm-up is promised or run (before: 'warm-up re-runs (20 s)', 'the
    warm-up (20 s, step 1) runs again first, then step 4 is sampled again')."""
    res, points, seg, t, restart, said = _power_loss_run(tmp_path, after_window("orientation", finished=2), 0.5, lag_s=0.015)
    assert _pairs(seg) == [("warmup", 0, "complete"), ("orientation", 1, "complete"),
                           ("orientation", 2, "complete"), ("orientation", 3, "complete")], _pairs(seg)
    assert restart[0] >= seg["t_end"][-1], restart
    assert "after step 4's window, the last;" in restart[1] and "last complete step 4 (" in restart[1], restart
    assert "no step runs after it" in restart[1] and "warm-up" not in restart[1], restart
    assert "no step runs after it" in said and "runs again" not in said and "sampled again" not in said, said
    assert points.engine.rewarm is None


def test_a_restart_during_the_move_to_the_next_orientation_rewarms_then_runs_it(tmp_path):
    """The power lost for 3 s as the third step starts (before its command): the link drop pauses
    the run during the table's move, before step 3 sampled anything; the restart is noticed in
    the pause. The event and the run log say it came before step 3's window and that the warm-up
    runs again first, then step 3 -- not that step 3 is 'sampled again' (it never was)."""
    from hil_support import starting
    res, points, seg, t, restart, said = _power_loss_run(tmp_path, starting("orientation", finished=1), 3.0)
    assert _pairs(seg) == [("warmup", 0, "complete"), ("orientation", 1, "complete"),
                           ("warmup", 0, "complete"), ("orientation", 2, "complete"),
                           ("orientation", 3, "complete")], _pairs(seg)
    assert seg["t_end"][1] <= restart[0] <= seg["t_start"][2]
    assert abs(seg["t_end"][2] - seg["t_start"][2] - WARMUP_S) < 1e-6
    assert "last complete step 2 (" in restart[1] and "warm-up re-runs (20 s)" in restart[1], restart
    assert "sampled again" not in said and "the warm-up (20 s, step 1) runs again first, then step 3 runs" in said, said


def test_a_restart_after_a_rewarms_window_warms_the_imu_again(tmp_path):
    """Power lost for 3 s in the second orientation (step 3): the re-warm runs; the power lost
    again for 0.5 s as that re-warm's window ends, noticed while its last samples are awaited
    (15 ms link latency). The re-warm is complete (its samples cover it), and the second restart
    lies after it, before step 3: a second whole re-warm runs before step 3 is sampled. Before,
    run() cleared the re-warm it asked for once the first re-warm's segment was recorded, and
    step 3 was measured on the unit just powered up again."""
    from hil_support import sampling
    res, points, seg, t, restarts, said = _power_loss_run(
        tmp_path, sampling("orientation", after_samples=100, finished=1), 3.0, lag_s=0.015,
        more=[(after_window("warmup", finished=1), 0.5)])
    assert _pairs(seg) == [("warmup", 0, "complete"), ("orientation", 1, "complete"),
                           ("orientation", 2, "incomplete"), ("warmup", 0, "complete"),
                           ("warmup", 0, "complete"), ("orientation", 2, "complete"),
                           ("orientation", 3, "complete")], _pairs(seg)
    (t1, first), (t2, second) = restarts
    assert "in step 3 (" in first
    assert "after step 1's window, before step 3;" in second and "last complete step 1 (" in second, second
    assert "warm-up re-runs (20 s)" in second
    assert "runs again first, then step 3 runs" in said[1], said[1]
    assert seg["t_end"][3] <= t2 <= seg["t_start"][4]       # between the two re-warms
    for i in (3, 4):
        assert abs(seg["t_end"][i] - seg["t_start"][i] - WARMUP_S) < 1e-6
    assert seg["t_end"][4] <= seg["t_start"][5]
    assert points.engine.rewarm is None


#: PROC with a chamber-set between its second and third orientations (steps 4 and 5)
CHAMBER_PROC = PROC.replace(", [180, 0, 0]]", "]") + "  - chamber-set: {setpoint_c: 25, label: set 25 degC}\n" + \
    PROC[PROC.index("  - orientations:"):].replace("[[0, 0, 0], [90, 0, 0], [180, 0, 0]]", "[[180, 0, 0]]")
#: the emulated chamber of tests/test_thermal_restart.py
CHAMBER_SIM = {"chamber__sim": {"heat_max_c_per_min": 20, "cool_max_c_per_min": 20, "product_tau_s": 20}}


def test_a_restart_before_a_chamber_step_says_the_rewarm_comes_after_it(tmp_path):
    """The power lost for 0.5 s as step 3's window ends (the last orientation before a
    chamber-set, step 4; 15 ms link latency): step 3 is complete, and run() runs the chamber
    step first -- re-warms are for the steps that measure -- then the warm-up, then step 5. The
    event and the run log say exactly that order (before: 'then step 4 runs' after the warm-up,
    and 'warm-up re-runs (20 s)' as if it preceded step 4)."""
    res, points, seg, t, restart, said = _power_loss_run(
        tmp_path, after_window("orientation", finished=1), 0.5, lag_s=0.015, proc_text=CHAMBER_PROC,
        cfg_extra=CHAMBER_SIM)
    assert _pairs(seg) == [("warmup", 0, "complete"), ("orientation", 1, "complete"),
                           ("orientation", 2, "complete"), ("chamber-set", 3, "complete"),
                           ("warmup", 0, "complete"), ("orientation", 4, "complete")], _pairs(seg)
    assert seg["t_end"][2] <= restart[0] <= seg["t_start"][3], restart
    assert abs(seg["t_end"][4] - seg["t_start"][4] - WARMUP_S) < 1e-6
    assert "after step 3's window, before step 4;" in restart[1], restart
    assert "warm-up re-runs (20 s) before step 5" in restart[1], restart
    assert ("step 4 (chamber-set) runs, then the warm-up (20 s, step 1) runs again, then step 5 runs"
            in said), said
    assert points.engine.rewarm is None


def test_a_restart_when_the_run_is_aborted_awaiting_a_windows_tail_says_the_run_stops(tmp_path):
    """The power lost for 0.5 s as step 3's window ends (15 ms link latency: the engine awaits
    the window's last samples), and an abort (``rigctl abort``: Engine.request_abort) in the very
    poll that notices the restart: the run stops there, step 3 not recorded complete. The event
    and the run log say the run stops and that a resumed run warms up first, then runs step 3
    again (before: 'in step 3; ...; the warm-up runs again first, then step 3 is sampled again',
    as if this run went on). ``rigctl resume`` then does what they said: the whole 20 s warm-up,
    then steps 3 and 4; the rows step 3 had are marked incomplete."""
    def noticed(engine, pts) -> bool:         # the poll that notices the restart, in the tail wait
        return engine._awaiting_tail and engine._tail_restart is not None
    also = [(noticed, lambda points: lambda: points.engine.request_abort("operator abort"))]
    res, points, seg, t, restart, said = _power_loss_run(
        tmp_path, after_window("orientation", finished=1), 0.5, lag_s=0.015, also=also, complete=False)
    assert res.status == "interrupted", (res.status, res.message)
    assert len(points.fired) == 2, points.fired
    assert _pairs(seg) == [("warmup", 0, "complete"), ("orientation", 1, "complete")], _pairs(seg)
    assert "in step 3 (" in restart[1] and "last complete step 2 (" in restart[1], restart
    assert "warm-up re-runs" not in restart[1] and "sampled again" not in said, (restart, said)
    assert ("the run stops before step 3 is recorded complete; a resumed run ('rigctl resume') re-runs the "
            "warm-up (20 s, step 1) first, then runs step 3 again") in said, said
    # the event says it too, whole, within the 200 bytes of /events/message (before: cut at byte
    # 200, '... a resumed run ('rigctl resume') re-runs the warm-u', the what-to-do lost)
    assert restart[1].endswith("; the run stops; 'rigctl resume' re-runs the warm-up (20 s, step 1) first, "
                               "then step 3"), restart
    assert len(restart[1].encode()) <= 200
    assert points.engine.rewarm is None       # nothing more runs in this session
    cut = len(seg["kind"])

    again = resume_run(res.run_dir, tmp_path / "runs", console=io.StringIO(), install_signals=False,
                       options=RunOptions(suspenders=SuspenderSettings(hold_s=1.0, min_free_bytes=0)))
    assert again.exit_code == 0 and again.status == "complete", again.message
    seg, t, events = _read(res.recording)
    assert _pairs(seg)[cut:] == [("orientation", 2, "incomplete"), ("warmup", 0, "complete"),
                                 ("orientation", 2, "complete"), ("orientation", 3, "complete")], _pairs(seg)
    assert abs(seg["t_end"][cut + 1] - seg["t_start"][cut + 1] - WARMUP_S) < 1e-6


#: PROC with a long warm-up label (non-ASCII: 2 bytes a character)
LONG_LABEL = "warm-up of the unit under test at 25 \u00b0C, bench 3, fixture B (" + "\u00e9" * 120 + ")"
LONG_PROC = PROC.replace("      duration: 20 s\n", f"      duration: 20 s\n      label: '{LONG_LABEL}'\n", 1)


def test_long_step_labels_are_shortened_in_the_events_never_what_to_do(tmp_path):
    """A 185-character warm-up label, the power lost during the second orientation: the re-warm
    event ('re-warm: step 1 (LABEL, 20 s) again, WHY; then step 3 (LABEL)') is over the 200 bytes
    of /events/message. Its labels are shortened with an ellipsis, the step that runs next named
    whole; every event fits and is whole UTF-8. Before: the message was cut at byte 200, inside
    the warm-up label ('then step 3' lost, a 2-byte character cut in two)."""
    res, points, seg, t, restart, said = _power_loss_run(
        tmp_path, sampling("orientation", after_samples=100, finished=1), 3.0, proc_text=LONG_PROC)
    with h5py.File(res.recording, "r") as f:
        raw = [bytes(m) for m in f["events/message"][()]]
        labels = f["segments/label"][()]
    assert all(len(m) <= 200 for m in raw)
    msgs = [m.decode("utf-8") for m in raw]            # strict: no character cut in two
    label3 = labels[list(seg["step"]).index(2)].decode()   # step 3's label, as recorded
    (rewarm,) = [m for m in msgs if m.startswith("re-warm: ")]
    assert rewarm.endswith(f"; then step 3 ({label3})"), rewarm
    head = "re-warm: step 1 ("
    assert rewarm.startswith(head + LONG_LABEL[:20]) and "\u2026" in rewarm, rewarm
    # a label shortened keeps its beginning: what is left of it is the label's start
    kept = rewarm[len(head):rewarm.index("\u2026")]
    assert kept and LONG_LABEL.startswith(kept), kept
    # the restart event: whole (short labels here), what the engine then does at its end
    assert restart[1].endswith("warm-up re-runs (20 s) before step 3"), restart
