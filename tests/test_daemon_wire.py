"""Unattended operation over the wire: `rigctl run` / `rigctl resume` as real processes against
the emulated hardware (sim/hardware.py: the ACL table and the Xsens IMU on ptys, the NovAtel
receiver on a pty, one physics world on a scaled clock) running in this test's process, and the
engine's suspenders seen through the real drivers.

Data at risk after ``kill -9`` is measured against what the emulator put on the wire: it keeps
the IMU batches it wrote (wall time, float32 accelerometer values as sent), so the newest row
in the file is found among them and ``lost = t_kill - (wall time it was sent)``, counted from
the moment the killed session's stream began (frames sent while no rigctl process was running
are the downtime's gap, not data the kill lost).
"""
from __future__ import annotations

import io
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from rigctl.recording.checkpoint import status_flags
from rigctl.config.config import load_config
from rigctl.engine.procedure import load_procedure
from rigctl.run.runner import RunOptions, resume_run, run_procedure

from helpers import DURATION_EPS, ROOT, make_cut_off, rigctl_cmd

from hil_support import commands_since, sent_time_of, table_snapshot, wait_progress, wait_until, wired

SPEED = 500.0          # rig seconds per wall second
KILLS = 20
CAPTURE = """procedure: overnight-capture
description: accelerated overnight capture (warm-up, then a long static capture)
defaults:
  settle: {timeout: 30 min}      # 3.6 s of wall time at 500x: a loaded machine never times out
steps:
  - warmup:
      duration: 30 s
  - capture:
      duration: 20 min
      label: overnight static
"""


def _swmr(path: Path) -> h5py.File:
    return h5py.File(path, "r", libver="latest", swmr=True)


def _open_cut_off(path: Path, tmp: Path, kill: int, window_hits: list[int]) -> h5py.File:
    """The recording after a kill, opened with h5py as a reader would (SWMR read: the dead
    writer's flags are still set). A kill at any moment, a resume's reopen included (the
    recorder reopens straight into SWMR-write mode), leaves a file that this open accepts."""
    return _swmr(path)


def _launch(args: list[str], log: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([*rigctl_cmd(), *args], cwd=ROOT, env=env, stdout=log.open("w"),
                            stderr=subprocess.STDOUT)


class _RunQueueWait:
    """How long a process's main thread (the engine, which flushes the recorder) waited for a
    CPU while runnable: /proc/PID/schedstat's second field, sampled every 10 ms by a thread.
    On an idle machine it stays near zero; on a loaded one it is the wall time the process could
    not use, so a wall-time bound on its work is measured against the time it had."""

    def __init__(self, pid: int) -> None:
        self.path, self.samples = Path(f"/proc/{pid}/schedstat"), [(time.monotonic(), 0.0)]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.01):
            try:
                wait_s = int(self.path.read_text().split()[1]) * 1e-9
            except (OSError, ValueError, IndexError):
                return                                  # the process is gone
            self.samples.append((time.monotonic(), wait_s))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def between(self, t0: float, t1: float) -> float:
        """Seconds the main thread waited for a CPU between wall times t0 and t1 (interpolated)."""
        t, w = np.array(self.samples).T
        return float(np.interp(t1, t, w) - np.interp(t0, t, w))

    def cpu_s(self) -> float:
        """The process's CPU time so far (all threads), s: progress while it starts or runs."""
        try:
            f = (self.path.parent / "stat").read_text().rsplit(")", 1)[1].split()
            return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")
        except (OSError, ValueError, IndexError):
            return -1.0


def test_kill9_chain_over_the_wire_loses_under_1s_and_resume_completes(tmp_path):
    """`rigctl run` of an accelerated overnight capture over ptys is killed with SIGKILL at 20
    random (seeded) moments -- run, kill, resume, kill, ... -- and finally completes. After
    every kill h5py opens the file, at most 1 s (wall) of the IMU data the emulator sent is
    missing from it, everything flushed is intact; the emulator's table is left as the kill
    found it (servo on, holding) and each resume commands it to stop before any motion. On a
    loaded machine the 1 s is of the time the process could run: the wall time its engine thread
    waited for a CPU in that window is added (_RunQueueWait; about 0 when the machine is idle),
    and the waits for a session last as long as its process makes progress (CPU time)."""
    rng = random.Random(8_2024)
    proc = tmp_path / "overnight.yaml"
    proc.write_text(CAPTURE)
    runs = tmp_path / "runs"
    with wired(tmp_path, SPEED, hw_kw={"imu_keep_sent": 4000}, suspenders={"min_free_mib": 0}) as (hw, cfg):
        args = ["run", str(proc), "--config", str(cfg), "--out", str(runs)]
        rec: Path | None = None
        n_rows, kills, window_hits = 0, [], []
        for i in range(KILLS + 1):
            starts = len(hw.xsens.measurement_starts)
            t_launch = time.monotonic()
            p = _launch(args, tmp_path / f"session{i + 1}.log")
            rq = _RunQueueWait(p.pid)
            try:
                if i == KILLS:
                    t_final = t_launch
                    wait_progress(lambda: p.poll() is not None, rq.cpu_s, f"session {i + 1} to complete", 60.0)
                    assert p.returncode == 0, (tmp_path / f"session{i + 1}.log").read_text()[-3000:]
                    break
                # the session's IMU stream began (the driver configured the device) ...
                wait_progress(lambda: len(hw.xsens.measurement_starts) > starts, rq.cpu_s,
                              f"session {i + 1}'s IMU stream")
                t_stream = hw.xsens.measurement_starts[starts]
                if rec is None:        # the chain resumes a recording: the first session makes it
                    rec = wait_progress(lambda: next(runs.glob("*/recording.h5"), None), rq.cpu_s,
                                        "the recording")
                # ... then a random moment of the run: connect, reopen, warm-up or capture
                time.sleep(rng.uniform(0.0, 2.0))
                assert p.poll() is None, f"session {i + 1} ended before its kill"
                t_kill = time.monotonic()
                os.kill(p.pid, signal.SIGKILL)
                p.wait(timeout=10)
            finally:
                rq.stop()
                if p.poll() is None:
                    p.kill()
            time.sleep(0.05)           # the controller finishes the line it was executing
            t_snap = time.monotonic()
            left = table_snapshot(hw)  # nothing stops the table: the emulator keeps the last demand
            args = ["resume", str(rec.parent), "--runs", str(runs)]
            with _open_cut_off(rec, tmp_path, i + 1, window_hits) as f:
                assert f["run/status"][0] == b"running"
                for g in ("imu", "table", "segments", "events"):
                    lengths = {f[g][k].shape[0] for k in f[g]}
                    assert len(lengths) == 1, f"kill {i + 1}: {g} columns of unequal length {lengths}"
                n = f["imu/time"].shape[0]
                c = f["imu/counter"][()].astype(np.int64)
                t = f["imu/time"][()]
                assert np.all(np.diff(c) > 0) and np.all(np.diff(t) > 0), f"kill {i + 1}: IMU rows out of order"
                last = f["imu/specific_force"][n - 1] if n else None
                n_resumes = int(np.sum(f["events/kind"][()] == b"resume"))
                n_stops = sum(b"stop commanded before any motion" in m for m in f["events/message"][()])
            if n > n_rows:             # rows of this session reached the file: when were they sent?
                w_last = sent_time_of(hw, last)
                assert w_last is not None, f"kill {i + 1}: the newest recorded row was never sent recently"
            else:
                w_last = -np.inf
            lost = t_kill - max(w_last, t_stream)
            starved = rq.between(max(w_last, t_stream), t_kill)
            unsent = sum(len(b[1]) for b in list(hw.xsens.sent) if max(w_last, t_stream) < b[0] <= t_kill)
            kills.append({"after_s": t_kill - t_launch, "lost_s": lost, "starved_s": starved, "rows_lost": unsent, "rows": n,
                          "table": left, "t_launch": t_launch, "t_kill": t_kill, "t_snap": t_snap,
                          "reopened": n_resumes > (kills[-1]["resumes"] if kills else 0), "resumes": n_resumes,
                          "stopped": n_stops > (kills[-1]["stops"] if kills else 0), "stops": n_stops})
            assert lost <= 1.0 + starved, (f"kill {i + 1}: {lost:.3f} s of sent IMU data not in the file "
                                           f"({starved:.3f} s of it the process waited for a CPU)")
            n_rows = n
        # every session after a kill commanded a stop before its first motion command. A session
        # is what the controller executed between its process's launch and its own kill: lines
        # the killed process had already written can still execute just after t_kill, and they
        # are not the next session's (that one is launched after the checks above)
        cmds = commands_since(hw, kills[0]["t_kill"])
        for k, nxt in zip(kills, kills[1:] + [{"t_launch": t_final, "t_kill": np.inf}]):
            session = [c for t, c in cmds if nxt["t_launch"] < t < nxt["t_kill"]]
            motion = [j for j, c in enumerate(session) if ":MODE:POSITION" in c or ":DEMAND" in c]
            stop = [j for j, c in enumerate(session) if c.startswith(":MODE:OFF")]
            if motion:
                assert stop and stop[0] < motion[0], session[:20]
            # ... and until then the table stayed as the kill left it: the mode of the last mode
            # command the controller executed before the snapshot (which can be one the killed
            # process wrote just before its kill)
            before = [c for t, c in commands_since(hw, k["t_launch"]) if t < k["t_snap"] and ":MODE:" in c]
            if before:
                want = "off" if before[-1].startswith(":MODE:OFF") else "position"
                assert k["table"]["mode"] == [want] * 3, (before[-1], k["table"])
        held = [k for k in kills if k["table"]["mode"] == ["position"] * 3]
        assert held and all(k["table"]["status"][a] & 0x2 for k in held for a in range(3))  # servo on
    # the chain completed into the same recording; its complete segments are all-or-nothing
    with h5py.File(rec, "r") as f:     # plain open: the flags are cleared, the file closed properly
        assert f["run/status"][0] == b"complete"
        seg = {k: f["segments"][k][()] for k in f["segments"]}
        c = f["imu/counter"][()].astype(np.int64)
        ev = list(zip(f["events/kind"][()], f["events/message"][()]))
    done = seg["status"] == b"complete"
    assert sorted(seg["kind"][done].tolist()) == [b"capture", b"warmup"]
    for a, z in zip(seg["first_sample"][done], seg["last_sample"][done]):
        assert z > a and np.all(np.diff(c[a:z]) == 1)
    cap = int(np.flatnonzero(done & (seg["kind"] == b"capture"))[0])
    # 1200 s to float rounding (t_end = t_start + 1200 s; a resumed session offsets both ends)
    assert seg["t_end"][cap] - seg["t_start"][cap] >= 1200.0 - DURATION_EPS
    assert seg["last_sample"][cap] - seg["first_sample"][cap] >= 0.99 * 1200 * 100
    for i in np.flatnonzero(~done):   # rows of cut-off steps are in no complete segment
        for j in np.flatnonzero(done):
            assert seg["last_sample"][i] <= seg["first_sample"][j] or seg["first_sample"][i] >= seg["last_sample"][j]
    # a kill before a session reopened the recording leaves no trace in it; the others wrote
    # their resume event, and (unless killed before) stopped the table before moving it
    reopened = 1 + sum(k["reopened"] for k in kills[1:])
    stopped = 1 + sum(k["stopped"] for k in kills[1:])
    resumes = [m for k, m in ev if k == b"resume" and b"after a cut-off" in m]
    stops = [m for k, m in ev if k == b"safe-state" and b"stop commanded before any motion" in m]
    assert len(resumes) == reopened and len(stops) == stopped and stopped >= KILLS // 2
    ck = json.loads((rec.parent / "checkpoint.json").read_text())
    # (a session killed before its first flush counted itself in the checkpoint, not in the file)
    assert ck["status"] == "complete" and reopened + 1 <= ck["sessions"] <= KILLS + 1
    assert resumes[-1].startswith(f"session {ck['sessions']} after a cut-off".encode())
    lost = [k["lost_s"] for k in kills]
    print(f"\nkill -9 x{KILLS}: data lost max {max(lost):.3f} s, mean {np.mean(lost):.3f} s (wall); "
          f"rows lost max {max(k['rows_lost'] for k in kills)}; kill moments "
          f"{min(k['after_s'] for k in kills):.2f}..{max(k['after_s'] for k in kills):.2f} s after launch; "
          f"{reopened - 1} of {KILLS - 1} resumed sessions reopened the file before their kill; "
          f"table left {sorted({k['table']['mode'][0] for k in kills})}; lost per kill "
          f"{[round(x, 2) for x in lost]}; waited for a CPU {[round(k['starved_s'], 2) for k in kills]}")
    assert not window_hits


def _pauses(ev_t: np.ndarray, kinds: np.ndarray, msgs: np.ndarray) -> list[dict]:
    """The recording's pauses in event order: each from the suspend that began it to ITS OWN
    resume (the suspend events between them are suspenders that tripped while it was paused).
    Per pause: first_event (the index of its first suspend among the events), t0, t1 (rig
    time, s; t_last: its last suspend's), names (all suspenders of the pause), the step it
    re-ran (0-based), cut ("sampling": the step's window was cut off, "before sampling", None),
    rows (the IMU rows [first, last) of the window it cut off, else None) and the resume
    message. A resume names exactly the suspenders of its pause; a suspend outside a pause or a
    resume without one fails."""
    def names(m: bytes, sep: bytes) -> set[str]:
        return set(m.split(sep, 1)[0].decode().split(", "))

    out: list[dict] = []
    cur: dict | None = None
    for j, (t, k, m) in enumerate(zip(ev_t, kinds, msgs)):
        if k == b"suspend":
            if cur is None:
                cur = {"first_event": j, "t0": float(t), "names": set(), "cut": None, "rows": None}
            cur["names"] |= names(m, b": ")
            cur["t_last"] = float(t)
        elif k == b"incomplete" and cur is not None:
            cur["cut"] = "before sampling" if b"cut off before sampling" in m else "sampling"
            if b"IMU rows [" in m:
                cur["rows"] = tuple(int(x) for x in m.split(b"IMU rows [", 1)[1].split(b")", 1)[0].split(b", "))
        elif k == b"resume":
            assert cur is not None, f"a resume outside any pause: {m!r}"
            assert names(m, b" clear for ") == cur["names"], (m, cur)
            assert b"re-running step " in m, m
            cur.update(t1=float(t), resume=m, step=int(m.split(b"re-running step ", 1)[1].split()[0]) - 1)
            out.append(cur)
            cur = None
    assert cur is None, f"a pause without its resume: {cur}"
    return out


def _show(pauses: list[dict]) -> list[str]:
    """The pauses, one line each (assertion messages)."""
    return [f"{p['t0']:.1f}-{p['t1']:.1f} step {p['step'] + 1} {sorted(p['names'])} cut {p['cut']}"
            for p in pauses]


def _check_drops_recorded(recording: Path, dropped: list[int]) -> np.ndarray:
    """The recording of the link-drop run below (``dropped``: the steps whose window lost its
    link, 0-based): its pauses, segments and data gaps (see the comments); returns the gaps
    (missing samples after each row)."""
    with h5py.File(recording, "r") as f:
        kinds, msgs = f["events/kind"][()], f["events/message"][()]
        seg = {k: f["segments"][k][()] for k in f["segments"]}
        counter = f["imu/counter"][()].astype(np.int64)
        imu_t, ev_t = f["imu/time"][()], f["events/time"][()]
    pauses = _pauses(ev_t, kinds, msgs)
    # each drop: one imu-link pause that cut the step off while it sampled, with its own resume,
    # one per dropped step (on a loaded host the engine may see the samples missing before it
    # sees the link down: the pause then begins with imu-gap and imu-link joins it)
    drops = [p for p in pauses if "imu-link" in p["names"] and p["cut"] == "sampling"]
    assert sorted(p["step"] for p in drops) == sorted(dropped), _show(pauses)
    # ... and every pause held until all was clear for the config's hold_s (2 s of rig time)
    assert all(b" clear for 2 s after " in p["resume"] and p["t1"] - p["t_last"] >= 2.0 - 1e-6
               for p in pauses), _show(pauses)
    # any other pause is the run's own account of a host too slow for the clock, never a pause
    # for something else: (a) the same drop's outage seen again right after its resume, which
    # cuts the step's re-run off before it sampled, on imu-link or imu-gap only (imu-link now
    # holds until the driver is configured again and streams, so a resume no longer comes before
    # the reconfiguration, whose GoToConfig..GoToMeasurement gap is the pause's. An imu-gap
    # 'inside a read' well after a resume -- seen at load 8-26: 26333 samples, IMU time 1454 ->
    # 1718 s, the pause having resumed at 1441 s -- was the emulator's port dropping bytes while
    # the driver waited for them (a master without room for 1.5 s, the client's queue empty: the
    # host, not the client; sim/links.py, tests/test_pty_host_stall.py), no longer); or (b) a window the
    # lagging IMU stream left without its samples, which the run said in a 'short-window' event
    # just before ('the IMU stream lags or stopped': the emulator, in this process, computed its
    # samples more than 1.5 s of wall time behind the clock) and samples again; or (c) after the
    # run recorded that the rig's devices keep time slower than its clock (a 'clock' event), an
    # IMU pause (imu-gap, imu-link, imu-window)
    # (in event order: a 'clock' event carries the devices' time, which lags the run's clock)
    slow_from = int(np.flatnonzero(kinds == b"clock")[0]) if np.any(kinds == b"clock") else len(kinds)
    for prev, p in zip([None, *pauses], pauses):
        if p in drops:
            continue
        seen_again = (prev is not None and p["step"] == prev["step"] and p["cut"] == "before sampling"
                      and p["names"] <= {"imu-link", "imu-gap"})
        j = max(i for i in range(p["first_event"]) if kinds[i] != b"state")   # (state changes between)
        lagged = (p["names"] == {"imu-window"} and kinds[j] == b"short-window"
                  and msgs[j].startswith(f"step {p['step'] + 1} (".encode()) and b"the IMU stream lags" in msgs[j])
        too_slow = p["first_event"] > slow_from and p["names"] <= {"imu-link", "imu-gap", "imu-window"}
        assert seen_again or lagged or too_slow, (p, _show(pauses))
    done_ = seg["status"] == b"complete"
    assert sorted(seg["step"][done_].tolist()) == list(range(10))        # one complete per step
    assert set(seg["step"][~done_].tolist()) <= set(dropped)             # the cut-off windows
    cut = [m for k, m in zip(kinds, msgs) if k == b"incomplete"]
    assert sorted({int(m.split()[1]) - 1 for m in cut}) == sorted(dropped)  # each drop cut its step off
    for a, z in zip(seg["first_sample"][done_], seg["last_sample"][done_]):
        assert z - a >= 0.9 * 10 * 100 and np.all(np.diff(counter[a:z]) == 1)
    # the samples missing (the outage, then the device reconfiguration after the reconnect:
    # no frames between GoToConfig and GoToMeasurement) all end in time the run set aside: the
    # first sample after a gap lies between the first sample of the window a pause cut off (its
    # 'incomplete' event's rows; the pause's start for one that cut nothing) and that pause's
    # resume -- or the run paused on the gap itself (an imu-gap suspend names that counter
    # jump). Not from the suspend event's time: the engine pauses on a link lost in the wait for
    # a window's last samples once that wait ends (up to engine.WINDOW_WAIT_WALL_S = 1.5 s of
    # wall time, 30 s of rig time at DROPS_SPEED), and on a loaded host a sample reaches the engine well after
    # its IMU time (so a pull also loses the samples still in flight from before the window)
    gaps = np.diff(counter) - 1
    named = {m.split(b"(counter ", 1)[1] for k, m in zip(kinds, msgs) if k == b"suspend" and b"(counter " in m}
    in_read = [int(m.split(b"IMU data gap: ", 1)[1].split()[0]) for k, m in zip(kinds, msgs)
               if k == b"suspend" and b"samples missing inside a read" in m]
    for i in np.flatnonzero(gaps > 0):
        set_aside = any((imu_t[p["rows"][0]] if p["rows"] else p["t0"]) <= imu_t[i + 1] <= p["t1"]
                        for p in pauses)
        reported = f"{counter[i]} -> {counter[i + 1]})".encode() in named or int(gaps[i]) in in_read
        assert set_aside or reported, (i, gaps[i], imu_t[i], imu_t[i + 1], _show(pauses))
    return gaps


ORIENT = """procedure: link-drops
steps:
  - orientations:
      angles_deg: [[0, 0, 0], [90, 0, 0], [0, 90, 0], [0, 0, 90], [180, 0, 0], [0, 180, 0],
                   [45, 45, 0], [0, 45, 45], [90, 90, 90], [0, 0, 0]]
      sample: 10 s
      discard: 0.5 s
      settle: {hold: 1 s, timeout: 60 s}
"""


def _pull_imu_in_windows(tmp_path: Path, proc_text: str, speed: float, hold: str, steps, into_window_s: float,
                         go_to_config_delay_s: float = 0.0):
    """Run ``proc_text`` over the wire at ``speed`` x (the IMU's link_timeout_s 0.05 s, the
    suspenders' hold_s ``hold``) and pull the IMU's pty for 0.2 s ``into_window_s`` of wall time
    into the sampling window of each step in ``steps`` (0-based; once each, while running);
    ``go_to_config_delay_s``: the emulated MTi's GoToConfig delay from the first pull on.
    Returns (the run's result, the steps pulled, the IMU driver, the emulator's reconnects, the
    console)."""
    proc_path = tmp_path / "drops.yaml"
    proc_path.write_text(proc_text)
    box: dict = {}
    done = threading.Event()
    dropped: list[int] = []
    todo = set(steps)

    def watch(hw) -> None:
        while not done.is_set() and len(dropped) < len(todo):
            e = box.get("engine")
            step = e.current_step if e is not None else None
            if step is not None and e.sampling_from is not None and step.index in todo \
                    and step.index not in dropped and e.states.state == "running":
                time.sleep(into_window_s)
                dropped.append(step.index)
                hw.imu_server.go_to_config_delay_s = go_to_config_delay_s
                hw.disconnect("imu", down_s=0.2)     # closes the pty now; new pty after 0.2 s
            time.sleep(0.001)

    def on_engine(e) -> None:
        box["engine"] = e
        if e is not None:
            box["imu"] = e.rig.imu

    with wired(tmp_path, speed, imu={"link_timeout_s": 0.05},
               suspenders={"hold_s": hold, "imu_timeout_s": 20}) as (hw, cfg_path):
        cfg = load_config(cfg_path)
        assert cfg.suspenders.imu_timeout_s == 20.0
        proc = load_procedure(proc_path, limits=cfg.limits)
        t = threading.Thread(target=watch, args=(hw,), daemon=True)
        t.start()
        console = io.StringIO()
        try:
            res = run_procedure(proc, cfg, tmp_path / "runs", console=console, install_signals=False,
                                options=RunOptions(on_engine=on_engine))
        finally:
            done.set()
            t.join()
        reconnects_emulator = hw.slots["imu"].reconnects
    return res, dropped, box["imu"], reconnects_emulator, console


#: the ten-drops run's clock, x real time. What it checks -- every drop detected, reconnected and
#: recorded, nothing lost unaccounted, nothing counted twice -- holds at any pace; the pace is the
#: host's. At 100x (a 100 Hz IMU: 10,000 frames per wall second through the emulator, the pty, the
#: driver and the recorder, all in this process on 2 cores) a host at load 17-30 kept the devices
#: at 46-56x: rigctl then stops the run, rightly, as an emulated rig slower than its clock ('the
#: rig's devices keep time at about 56x real time, slower than the 100x of the run's clock ...
#: restart it with --speed 20 or less'; 8 failures in 9 runs), which measured the host, not the
#: drops. 20x is what that message advises there, and takes less wall time on an idle host too
#: (16.5 s against 47 s at 100x, load 5: the outages' wall-time waits, not the rig time, set it).
DROPS_SPEED = 20.0


def test_ten_imu_link_drops_over_the_wire_reconnected_recorded_and_completed(tmp_path):
    """The emulator pulls the IMU's pty (closes it, opens a new one at the same symlink 0.2 s
    later) in the middle of each of 10 sampling windows: the Xsens driver reconnects and
    reconfigures every time, each drop is an `imu-link` suspender event, the interrupted step
    re-runs and the procedure completes with one complete, gap-free segment per step. Each pause
    is read with its own resume (_pauses); a loaded host adds pauses, each of which the run's own
    record explains (_check_drops_recorded), and every sample missing is in time it set aside.
    At DROPS_SPEED, a pace a loaded host keeps (see there)."""
    res, dropped, imu, reconnects_emulator, console = _pull_imu_in_windows(
        tmp_path, ORIENT, DROPS_SPEED, "2 s", steps=range(10), into_window_s=0.02)   # 0.4 s of rig time in
    assert res.exit_code == 0 and res.status == "complete", res.message
    assert sorted(dropped) == list(range(10))
    assert reconnects_emulator == 10
    c = imu.counters
    # every loss reconnected, and the device configured once per pull (and at the start): no
    # configured link was lost but by a pull. A loaded host can lose a reconnect's link again
    # before its configuration completes (the emulator answers GoToConfig too late: 'Write
    # timeout', seen at load 8-10): a loss and a reconnect more, not a configuration more
    assert c["link_losses"] == c["reconnects"] >= 10 and c["configurations"] == 11, c
    gaps = _check_drops_recorded(res.recording, dropped)
    assert "IMU link lost" in console.getvalue()
    print(f"\n10 IMU link drops: {int(gaps[gaps > 0].sum())} samples missing over the outages "
          f"({c['bad_frames'] + c['truncated_frames']} frames cut by the pulls), all 10 steps complete")


KILL_IN_REOPEN = """
import os, signal, sys, h5py
f = h5py.File(sys.argv[1], "r+", libver="latest")   # what Recorder.reopen does first ...
f["run/status"][0] = b"running"
f.flush()
os.kill(os.getpid(), signal.SIGKILL)                 # ... killed before 'f.swmr_mode = True'
"""


def test_resume_after_a_kill_inside_the_reopen_window(tmp_path):
    """A kill between a resume's plain 'r+' open and its switch to SWMR leaves the HDF5 write
    flag without the SWMR flag: no h5py reader accepts the file (the gap the kill chain above
    can hit; the fix belongs in rigctl/recording/recorder.py). `rigctl resume` still recovers the run."""
    cfg = load_config(ROOT / "configs" / "sim.yaml")
    proc_path = tmp_path / "p.yaml"
    proc_path.write_text("procedure: window\nsteps:\n  - warmup:\n      duration: 5 s\n"
                         "  - capture:\n      duration: 20 s\n")
    proc = load_procedure(proc_path, limits=cfg.limits)
    res = run_procedure(proc, cfg, tmp_path / "runs", console=io.StringIO(), install_signals=False)
    assert res.status == "complete"
    # make it a run cut off during its capture: checkpoint after step 1, no capture segment
    make_cut_off(res.run_dir, res.recording)
    r = subprocess.run([sys.executable, "-c", KILL_IN_REOPEN, str(res.recording)], capture_output=True)
    assert r.returncode == -signal.SIGKILL and status_flags(res.recording) == 1
    with pytest.raises(OSError, match="not already open for SWMR writing"):
        _swmr(res.recording)
    again = resume_run(res.run_dir, tmp_path / "runs", console=io.StringIO(), install_signals=False)
    assert again.status == "complete", again.message
    with h5py.File(res.recording, "r") as f:
        assert f["run/status"][0] == b"complete"
        done = f["segments/status"][()] == b"complete"
        assert sorted(f["segments/kind"][()][done].tolist()) == [b"capture", b"warmup"]


#: the first orientation of ORIENT
ORIENT_ONE = ORIENT.replace(ORIENT.split("angles_deg: ", 1)[1].split("\n      sample", 1)[0], "[[0, 0, 0]]")


def test_a_link_drop_with_a_slow_reconfiguration_resumes_once_when_the_stream_is_back(tmp_path):
    """The IMU's pty is pulled for 0.2 s, 1 s into a 10 s window (10x), and the emulated MTi
    takes 0.3 s of wall time to leave measurement mode on the reconnect's GoToConfig, streaming
    on meanwhile: the reconnecting driver hands out those frames, received before its
    reconfiguration. The pause ends only once the device is configured again and streams
    (imu-link kept tripped till then): one pause, with one resume, and the re-run samples its
    whole window. Before, the frames cleared 'imu-link' and the pause ended after hold_s (0.5 s
    of rig time, 50 ms of wall) while the driver was still reconfiguring: the re-run paused
    again on the same outage before it sampled (two resumes)."""
    # 1 s of rig time into the 10 s window; the delay below the driver's 0.5 s reply timeout
    res, dropped, imu, _, _ = _pull_imu_in_windows(tmp_path, ORIENT_ONE, 10.0, "0.5 s", steps=[0],
                                                   into_window_s=0.1, go_to_config_delay_s=0.3)
    assert res.exit_code == 0 and res.status == "complete", res.message
    assert dropped == [0]
    c = imu.counters
    assert c["link_losses"] == c["reconnects"] == 1 and c["configurations"] == 2, c
    with h5py.File(res.recording, "r") as f:
        kinds, msgs, ev_t = f["events/kind"][()], f["events/message"][()], f["events/time"][()]
        seg = {k: f["segments"][k][()] for k in f["segments"]}
        counter = f["imu/counter"][()].astype(np.int64)
        imu_t = f["imu/time"][()]
    pauses = _pauses(ev_t, kinds, msgs)
    assert len(pauses) == 1, _show(pauses)
    # the stream was back before the run resumed: the first sample after each counter gap (the
    # outage; then the reconfiguration, no frames from GoToConfig to GoToMeasurement) came first
    gaps = np.flatnonzero(np.diff(counter) > 1)
    assert gaps.size and np.all(imu_t[gaps + 1] < pauses[0]["t1"]), (imu_t[gaps + 1], _show(pauses))
    (p,) = pauses
    assert "imu-link" in p["names"] and p["cut"] == "sampling" and p["step"] == 0, _show(pauses)
    done_ = seg["status"] == b"complete"
    assert seg["step"][done_].tolist() == [0] and seg["step"][~done_].tolist() == [0]
    for a, z in zip(seg["first_sample"][done_], seg["last_sample"][done_]):
        assert z - a >= 0.9 * 10 * 100 and np.all(np.diff(counter[a:z]) == 1)
