"""Suspenders on the in-process emulator with injected faults (sim/faults.py): IMU link drops,
a table fault in a rate step, a full disk, a temperature excursion, operator pause; and the
state machine's legal transitions."""
from __future__ import annotations

import io
import math
from contextlib import contextmanager
from pathlib import Path

import h5py
import numpy as np
import pytest

from rigctl.config.config import load_config
from rigctl.devices import AxisStatus
from rigctl.engine.procedure import load_procedure
from rigctl.engine.rig import open_rig
from rigctl.run.runner import RunOptions, run_procedure
from rigctl.engine.states import IllegalTransition, StateMachine
from rigctl.config.suspenders import SuspenderSettings

from helpers import DISK_PROCEDURE as DISK, ROOT, fill_disk

CFG = ROOT / "configs" / "sim.yaml"


def run_with_faults(tmp: Path, text: str, setup, settings: SuspenderSettings, out: Path | None = None):
    """Run procedure ``text`` on the emulator; ``setup(faults, rig, state)`` schedules faults."""
    cfg = load_config(CFG)
    proc_path = tmp / "proc.yaml"
    proc_path.write_text(text)
    proc = load_procedure(proc_path, limits=cfg.limits)
    transitions: list[tuple[str, str, str]] = []
    states = StateMachine()
    states.listeners.append(lambda o, n, r: transitions.append((o, n, r)))
    box: dict = {}

    @contextmanager
    def opener(c):
        with open_rig(c) as (rig, truth):
            box["faults"] = rig.table.world.faults
            setup(rig.table.world.faults, rig, box)
            yield rig, truth

    console = io.StringIO()
    opts = RunOptions(suspenders=settings, states=states, rig_opener=opener, max_pause_s=600)
    res = run_procedure(proc, cfg, out or tmp, console=console, install_signals=False, options=opts)
    return res, proc, box["faults"], transitions, console.getvalue()


def read(path: Path) -> dict:
    with h5py.File(path, "r") as f:  # plain open: the file was closed properly
        out = {f"{g}/{k}": f[g][k][()] for g in ("segments", "events", "table") for k in f[g]}
        out["counter"] = f["imu/counter"][()].astype(np.int64)
        out["imu_time"] = f["imu/time"][()]
        out["status"] = f["run/status"][0]
    return out


def check_segments_all_or_nothing(d: dict, proc) -> None:
    """Every motion step has exactly one complete segment, with no missing samples in it."""
    st, step = d["segments/status"], d["segments/step"]
    complete = st == b"complete"
    motion = [s.index for s in proc.steps if s.is_motion]
    assert sorted(step[complete].tolist()) == motion
    for a, z in zip(d["segments/first_sample"][complete], d["segments/last_sample"][complete]):
        assert np.all(np.diff(d["counter"][a:z]) == 1)
    assert set(st.tolist()) <= {b"complete", b"incomplete"}


ORIENT = """procedure: drops
steps:
  - orientations:
      angles_deg: [[0, 0, 0], [90, 0, 0], [0, 90, 0], [0, 0, 90], [180, 0, 0], [0, 180, 0],
                   [45, 45, 0], [0, 45, 45], [90, 90, 90], [0, 0, 0]]
      sample: 6 s
      discard: 0.5 s
      settle: {hold: 1 s, timeout: 60 s}
"""


def test_ten_imu_link_drops_each_reconnected_recorded_and_procedure_completes(tmp_path):
    drops = [(12.0 + 10.0 * k, 1.5) for k in range(10)]

    def setup(faults, rig, box):
        for t, dur in drops:
            faults.schedule("imu_link", t, dur)

    res, proc, faults, transitions, console = run_with_faults(
        tmp_path, ORIENT, setup, SuspenderSettings(hold_s=2.0, min_free_bytes=0))
    assert res.exit_code == 0 and res.status == "complete", res.message
    assert faults.count("imu_link") == 10
    d = read(res.recording)
    kinds, msgs, times = d["events/kind"], d["events/message"], d["events/time"]
    link = [i for i, (k, m) in enumerate(zip(kinds, msgs)) if k == b"suspend" and m.startswith(b"imu-link")]
    assert len(link) == 10
    for (t_drop, dur), i in zip(drops, link):
        assert t_drop <= times[i] <= t_drop + 1.0  # noticed at the next poll
        later = [j for j in range(i + 1, len(kinds)) if kinds[j] == b"resume"]
        assert later and times[later[0]] >= t_drop + dur + 2.0  # reconnected, then clear for the hold
    assert sum(1 for o, n, _ in transitions if (o, n) == ("paused", "running")) == 10
    check_segments_all_or_nothing(d, proc)
    # no complete segment contains a moment when the link was down
    complete = d["segments/status"] == b"complete"
    for t0, t1 in zip(d["segments/t_start"][complete], d["segments/t_end"][complete]):
        assert all(t1 <= t or t0 >= t + dur for t, dur in drops)
    assert "IMU link lost" in console


RATE = """procedure: rate-fault
steps:
  - rates:
      axes: [z]
      rates_dps: [100]
      directions: [forward]
      dwell: 20 s
      discard: 0.5 s
      settle: {hold: 1 s, timeout: 60 s}
"""


def test_table_fault_mid_rate_step_stops_table_pauses_and_resumes_after_clear(tmp_path):
    t_fault, t_clear = 10.0, 30.0

    def setup(faults, rig, box):
        faults.schedule("table_fault", t_fault)  # until the operator clears it
        faults.call_at(t_clear, lambda: faults.clear("table_fault", t_clear))

    res, proc, faults, transitions, console = run_with_faults(
        tmp_path, RATE, setup, SuspenderSettings(hold_s=3.0, min_free_bytes=0))
    assert res.exit_code == 0 and res.status == "complete", res.message
    d = read(res.recording)
    t, rate, status = d["table/time"], d["table/rate"], d["table/status"].astype(np.int64)
    # spinning at 100 deg/s about the outer axis just before the fault
    before = (t > t_fault - 2) & (t < t_fault)
    assert np.all(np.abs(np.degrees(rate[before, 0]) - 100) < 0.1)
    # the fault bit is reported and the table is stopped within 1 s of the fault, until cleared
    during = (t >= t_fault + 1.0) & (t < t_clear)
    assert during.sum() > 20
    assert np.all(status[during] & int(AxisStatus.FAULT))
    assert np.all(np.abs(rate[during]) < math.radians(0.01))
    # the job paused with a clear message, and resumed only after the fault was cleared
    pauses = [r for o, n, r in transitions if n == "paused"]
    assert len(pauses) == 1 and "outer axis reports fault" in pauses[0] and "clear the fault" in pauses[0]
    assert "suspended (table)" in console
    resume_t = d["events/time"][d["events/kind"] == b"resume"]
    assert len(resume_t) == 1 and resume_t[0] >= t_clear + 3.0
    # the cut-off rate window is kept but marked incomplete; the re-run is complete and after it
    st = d["segments/status"]
    assert list(st) == [b"incomplete", b"complete"]
    assert d["segments/t_start"][1] > t_clear and d["segments/t_end"][0] < t_clear
    assert abs(np.degrees(d["segments/measured_rate"][1][0]) - 100) < 0.05
    check_segments_all_or_nothing(d, proc)


def test_temperature_excursion_and_operator_pause(tmp_path):
    def setup(faults, rig, box):
        faults.schedule("temperature", 12.0, 4.0, offset_c=80.0)  # 25 + 80 degC > 85 degC

    res, proc, faults, transitions, console = run_with_faults(
        tmp_path, ORIENT.replace("sample: 6 s", "sample: 3 s"), setup,
        SuspenderSettings(hold_s=1.0, min_free_bytes=0))
    assert res.status == "complete"
    d = read(res.recording)
    sus = [m for k, m in zip(d["events/kind"], d["events/message"]) if k == b"suspend"]
    assert len(sus) == 1 and sus[0].startswith(b"temperature: IMU temperature 105.0 degC outside")
    check_segments_all_or_nothing(d, proc)


def test_state_machine_only_legal_transitions():
    sm = StateMachine()
    seen = []
    sm.listeners.append(lambda o, n, r: seen.append((o, n)))
    for bad in ("paused", "pausing", "aborting"):
        with pytest.raises(IllegalTransition):
            sm.to(bad)
    for new in ("running", "pausing", "paused", "running", "aborting", "idle", "running", "faulted"):
        sm.to(new)
    with pytest.raises(IllegalTransition):
        sm.to("running")  # a faulted rig needs an operator reset first
    sm.to("idle", "reset")
    assert len(seen) == 9 and seen[-1] == ("faulted", "idle")


# -- a full disk ---------------------------------------------------------------------------------


def test_full_disk_pauses_with_clear_message_and_damages_nothing(tmp_path, small_fs):
    settings = SuspenderSettings(hold_s=2.0, min_free_bytes=1 << 20)
    ref, *_ = run_with_faults(tmp_path, DISK, lambda f, r, b: None, settings,
                              out=tmp_path / "ref")
    ballast = small_fs / "ballast"

    def fill() -> None:
        fill_disk(ballast)

    def setup(faults, rig, box):
        faults.call_at(16.0, fill)
        faults.call_at(40.0, ballast.unlink)

    res, proc, faults, transitions, console = run_with_faults(tmp_path, DISK, setup, settings,
                                                              out=small_fs)
    assert res.status == "complete", res.message
    pauses = [r for o, n, r in transitions if n == "paused"]
    assert pauses and "disk space low" in pauses[0] and "MiB free" in pauses[0]
    assert "suspended (disk)" in console
    d = read(res.recording)
    check_segments_all_or_nothing(d, proc)
    lost = [m for k, m in zip(d["events/kind"], d["events/message"]) if k == b"data-lost"]
    assert len(lost) == 1 and b"not recorded while the disk was full" in lost[0]
    # nothing already written is damaged: every row on disk before the disk filled up is
    # bit-identical to the same rows of an identical run without the fault
    with h5py.File(ref.recording, "r") as fr, h5py.File(res.recording, "r") as fx:
        n = fx["imu/counter"].shape[0]
        k = min(n, fr["imu/counter"].shape[0])
        t_full = 16.0
        upto = int(np.searchsorted(fr["imu/time"][()], t_full))
        assert 1000 < upto <= k
        for name in ("time", "counter", "specific_force", "angular_rate", "temperature"):
            np.testing.assert_array_equal(fx["imu"][name][:upto], fr["imu"][name][:upto])
        seg0 = {c: fx["segments"][c][0] for c in ("kind", "first_sample", "last_sample", "status")}
        assert seg0["kind"] == b"warmup" and seg0["status"] == b"complete"

