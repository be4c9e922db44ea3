"""Pause rules on the emulated rig in virtual time: a deferred pause waits for the end of the
step in flight (nothing is cut off), an immediate one cuts it off; a warm-up paused with the IMU
powered keeps the time it had done, one paused by an IMU link loss starts over."""
from __future__ import annotations

import io
import re
from contextlib import contextmanager
from pathlib import Path

import h5py
import numpy as np

from rigctl.config.config import load_config
from rigctl.engine.procedure import load_procedure
from rigctl.engine.rig import open_rig
from rigctl.run.runner import RunOptions, run_procedure
from rigctl.config.suspenders import SuspenderSettings

from helpers import ROOT

CFG = ROOT / "configs" / "sim.yaml"
HOLD = 1.0


def run(tmp: Path, text: str, schedule) -> dict:
    """Run ``text``; ``schedule(faults, box)`` sets up actions at rig times (box['engine'])."""
    cfg = load_config(CFG)
    tmp.mkdir(parents=True, exist_ok=True)
    path = tmp / "proc.yaml"
    path.write_text(text)
    proc = load_procedure(path, limits=cfg.limits)
    box: dict = {}

    @contextmanager
    def opener(c):
        with open_rig(c) as (rig, truth):
            box["world"] = rig.table.world
            yield rig, truth

    def on_engine(engine):
        if engine is not None:  # called again with None when the run ends
            box["engine"] = engine
            schedule(box["world"].faults, box)

    opts = RunOptions(suspenders=SuspenderSettings(hold_s=HOLD, min_free_bytes=0), rig_opener=opener,
                      on_engine=on_engine, max_pause_s=600)
    res = run_procedure(proc, cfg, tmp, console=io.StringIO(), install_signals=False, options=opts)
    assert res.exit_code == 0, res.message
    with h5py.File(res.recording, "r") as f:
        out = {k: f["segments"][k][()] for k in f["segments"]}
        out["events"] = [(float(t), k.decode(), m.decode()) for t, k, m in
                         zip(f["events/time"][()], f["events/kind"][()], f["events/message"][()])]
        out["imu_time"] = f["imu/time"][()]
    return out


ORIENT = """procedure: three
steps:
  - orientations:
      angles_deg: [[0, 0, 0], [90, 0, 0], [0, 90, 0]]
      sample: 20 s
      settle: {hold: 1 s, timeout: 60 s}
"""


def _pause_at(t: float, deferred: bool, resume_after: float):
    def schedule(faults, box):
        eng = box["engine"]
        faults.call_at(t, lambda: eng.request_pause("test pause", deferred=deferred))
        faults.call_at(t + resume_after, eng.request_resume)
    return schedule


def test_deferred_pause_waits_for_the_end_of_the_step_immediate_cuts_it_off(tmp_path):
    # the first step samples from about 1 s to 21 s of rig time: ask for the pause at 10 s
    deferred = run(tmp_path / "d", ORIENT, _pause_at(10.0, True, 40.0))
    status = deferred["status"].tolist()
    assert status == [b"complete"] * 3, status  # nothing cut off, nothing re-run
    sus = [t for t, k, m in deferred["events"] if k == "suspend" and "operator" in m]
    assert len(sus) == 1
    first_end, second_start = deferred["t_end"][0], deferred["t_start"][1]
    assert first_end <= sus[0] < second_start, (first_end, sus[0], second_start)
    assert sus[0] - first_end < 1.0  # at once after the step, not later
    resumed = [m for t, k, m in deferred["events"] if k == "resume"]
    assert len(resumed) == 1 and "starting step 2" in resumed[0]
    assert not [e for e in deferred["events"] if e[1] == "incomplete"]

    immediate = run(tmp_path / "i", ORIENT, _pause_at(10.0, False, 40.0))
    status = immediate["status"].tolist()
    assert status == [b"incomplete", b"complete", b"complete", b"complete"], status
    assert immediate["step"].tolist() == [0, 0, 1, 2]
    sus = [t for t, k, m in immediate["events"] if k == "suspend" and "operator" in m]
    assert len(sus) == 1 and immediate["t_start"][1] > sus[0] > 9.0  # cut off at about 10 s
    assert any("re-running step 1" in m for t, k, m in immediate["events"] if k == "resume")


WARM = """procedure: warm
steps:
  - warmup:
      duration: 60 s
  - orientations:
      angles_deg: [[90, 0, 0]]
      sample: 5 s
      settle: {hold: 1 s, timeout: 60 s}
"""


def _warm_segments(d: dict) -> tuple[list[tuple[float, float]], float]:
    """(start, end, status) of the warm-up's segments in order (start: the IMU time of its first
    sample; an incomplete segment records no window times), and the first suspension's time."""
    segs = [(float(d["imu_time"][i]), float(z), s) for i, z, s, k in
            zip(d["first_sample"], d["t_end"], d["status"], d["kind"]) if k == b"warmup"]
    sus = min(t for t, k, m in d["events"] if k == "suspend")
    return segs, sus


def test_warmup_keeps_its_time_when_the_imu_stayed_powered_and_starts_over_after_a_link_loss(tmp_path):
    # an IMU temperature excursion (the IMU stays powered) at 30 s: the warm-up keeps ~29 s
    hot = run(tmp_path / "t", WARM, lambda faults, box: faults.schedule("temperature", 30.0, 3.0, offset_c=80.0))
    segs, sus = _warm_segments(hot)
    (a0, _z0, s0), (a1, z1, s1) = segs
    assert (s0, s1) == (b"incomplete", b"complete")
    done_before = sus - a0            # warm-up sampled before the pause
    assert 25.0 < done_before < 31.0, done_before
    np.testing.assert_allclose(z1 - a1, 60.0 - done_before, atol=0.6)  # only what was left
    kept = [m for t, k, m in hot["events"] if k == "info" and "warm-up kept" in m]
    assert len(kept) == 1, kept
    assert abs(float(re.search(r"([\d.]+) s of warm-up kept", kept[0]).group(1)) - done_before) < 0.6, kept

    # an IMU link loss at 30 s (the IMU may have lost power): the whole 60 s again
    lost = run(tmp_path / "l", WARM, lambda faults, box: faults.schedule("imu_link", 30.0, 3.0))
    segs, sus = _warm_segments(lost)
    assert [s for *_, s in segs] == [b"incomplete", b"complete"]
    a1, z1, _ = segs[1]
    np.testing.assert_allclose(z1 - a1, 60.0, atol=0.6)
    assert not [m for t, k, m in lost["events"] if "warm-up kept" in m]
