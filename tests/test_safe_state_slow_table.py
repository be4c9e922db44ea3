"""The end-of-run safe state waits for the table on the table's own time, not on the run's clock.

tests/test_hil_pulses_config.py::test_sim_up_cli_serves_a_wired_run failed once at load ~20 with
'the table still reports motion after the stop command': the engine gave the table 2 s of the
run's clock to stop -- 20 ms of wall time at 100x -- while the emulator's physics, starved of
CPU, had not yet computed the table slowing down (0.25 s of table time from 100 deg/s at
400 deg/s^2). The host's stall is made deterministic here: the emulator's physics stops when the last step has
finished, just before the safe state's stop command, and goes on only once the controller has
answered HELD_READS table reads after that command (or after RELEASE_WALL_S of wall time, a
safety: the old code's wait gave up within 20 ms), so the table reports its rate with its time
standing still, then slows down and stops. Before, the stall was 0.5 s of wall time from the
step's end: on a host at load ~12 the engine took longer than that to reach the stop command,
the stall was over before the safe state read the table, and the test saw no held read (it
measured the host's speed, not the wait). A wired run at 100x on real ptys; ~5 s.
"""
from __future__ import annotations

import threading
import time

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

#: table reads after the stop command that the controller answers with its physics held back
HELD_READS = 4
#: the physics goes on after this much wall time even without those reads (well under the
#: engine's still_wall_s, 60 s, so the product's own wait is never what ends the hold)
RELEASE_WALL_S = 20.0


class _StallAtTheEnd(NullProgress):
    """Stops the emulator's physics when the last step has finished (in the engine's thread:
    before the safe state commands the stop) until the controller has received the stop command
    and then HELD_READS + 1 table reads: the reply to each of the first HELD_READS was computed
    with the physics standing still (the client sends a read only once it has the previous
    reply). Counted on the lines the emulated controller received, not on wall time."""

    def __init__(self, hw) -> None:
        super().__init__()
        self.hw, self.stalled, self.reads_held = hw, 0, 0
        self.thread: threading.Thread | None = None

    def step_finished(self, step, segment=None) -> None:
        self.hw.pause_physics(RELEASE_WALL_S)
        self.stalled += 1
        since = time.monotonic()
        self.thread = threading.Thread(target=self._release, args=(since,), daemon=True)
        self.thread.start()

    def _release(self, since: float) -> None:
        while time.monotonic() - since < RELEASE_WALL_S:
            lines = [line for t, line in list(self.hw.acl.core.received) if t >= since]
            stop = next((i for i, line in enumerate(lines) if line.startswith(":MODE:OFF")), None)
            if stop is not None:
                self.reads_held = sum(line.startswith(":READ:ALL?") for line in lines[stop + 1:])
                if self.reads_held > HELD_READS:
                    break
            time.sleep(0.002)
        self.hw.pause_physics(0.0)


def test_the_safe_state_waits_for_a_table_whose_physics_is_held_back(tmp_path):
    proc = tmp_path / "one-rate.yaml"
    proc.write_text(ONE_RATE)
    with wired(tmp_path, 100.0) as (hw, cfg_path):
        progress = _StallAtTheEnd(hw)
        res, _ = run(proc, cfg_path, tmp_path / "runs", {}, RunOptions(progress=progress))
        assert progress.stalled == 1
        progress.thread.join()
    assert res.status == "complete", res.message
    with h5py.File(res.recording, "r") as f:
        kinds, msgs = f["events/kind"][()], f["events/message"][()]
        t_table, rate = f["table/time"][()], f["table/rate"][()]
    assert [m for k, m in zip(kinds, msgs) if k == b"safe-state"] == [b"table stopped, servo off"]
    assert progress.reads_held > HELD_READS, progress.reads_held     # the stall as meant
    # the table was still turning (about 67 deg/s, the emulator's last tick before the stall) when
    # the stop was commanded, and the safe state recorded it through the stall -- reads of a
    # turning table whose time stood still -- until it read zero rate
    turning = np.degrees(np.abs(rate)).max(axis=1) > 10.0
    held = turning[1:] & turning[:-1] & (np.diff(t_table) < 1e-6)    # (its time base maps ms onto the run)
    assert held.sum() >= HELD_READS - 1, (t_table[-12:], np.degrees(rate[-12:]))
    assert not turning[-1]
