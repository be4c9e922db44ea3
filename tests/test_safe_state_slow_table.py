"""The end-of-run safe state waits for the table on the table's own time, not on the run's clock.

tests/test_hil_pulses_config.py::test_sim_up_cli_serves_a_wired_run failed once at load ~20 with
'the table still reports motion after the stop command': the engine gave the table 2 s of the
run's clock to stop -- 20 ms of wall time at 100x -- while the emulator's physics, starved of
CPU, had not yet computed the table slowing down (0.25 s of table time from 100 deg/s at
400 deg/s^2). The host's stall is made deterministic here: the emulator's physics stops for
0.5 s of wall time (50 s of the run's clock) just before the safe state's stop command, so the
table reports its rate with its time standing still, then slows down and stops. A wired run at
100x on real ptys; ~5 s.
"""
from __future__ import annotations

import h5py
import numpy as np

from rigctl.progress import NullProgress
from rigctl.run.runner import RunOptions

from hil_support import run, wired

ONE_RATE = """procedure: one-rate
steps:
  - rates:
      axes: [z]
      rates_dps: [100]
      directions: [forward]
      revolutions: 1
      discard: 0.5 s
      settle: {rate_window_dps: 0.05, hold: 1 s, timeout: 60 s}
"""

STALL_WALL_S = 0.5


class _StallAtTheEnd(NullProgress):
    """Stops the emulator's physics for STALL_WALL_S of wall time when the last step has
    finished (in the engine's thread: before the safe state commands the stop)."""

    def __init__(self, hw) -> None:
        super().__init__()
        self.hw, self.stalled = hw, 0

    def step_finished(self, step, segment=None) -> None:
        self.hw.pause_physics(STALL_WALL_S)
        self.stalled += 1


def test_the_safe_state_waits_for_a_table_whose_physics_is_held_back(tmp_path):
    proc = tmp_path / "one-rate.yaml"
    proc.write_text(ONE_RATE)
    with wired(tmp_path, 100.0) as (hw, cfg_path):
        progress = _StallAtTheEnd(hw)
        res, _ = run(proc, cfg_path, tmp_path / "runs", {}, RunOptions(progress=progress))
        assert progress.stalled == 1
    assert res.status == "complete", res.message
    with h5py.File(res.recording, "r") as f:
        kinds, msgs = f["events/kind"][()], f["events/message"][()]
        t_table, rate = f["table/time"][()], f["table/rate"][()]
    assert [m for k, m in zip(kinds, msgs) if k == b"safe-state"] == [b"table stopped, servo off"]
    # the table was still turning (about 67 deg/s, the emulator's last tick before the stall) when
    # the stop was commanded, and the safe state recorded it through the stall -- reads of a
    # turning table whose time stood still -- until it read zero rate
    turning = np.degrees(np.abs(rate)).max(axis=1) > 10.0
    held = turning[1:] & turning[:-1] & (np.diff(t_table) < 1e-6)    # (its time base maps ms onto the run)
    assert held.sum() >= 3, (t_table[-12:], np.degrees(rate[-12:]))
    assert not turning[-1]
