"""rigctl.analysis.restarts.restart_notes reads the events and the segments of a recording in
one opening of the file (before: three -- two for the events, one for the segments -- so a run
still writing could have its events and its segments read at different states).

The recording is written here with h5py (tests/recording_helpers.py, plus /segments and /events
in the recorder's layout): two orientation windows, a ``device-restart`` event between them, a
warm-up before. The opening is counted on the real reader (recording_reader._open_h5, still
called); the expected sides come from the table written here.
"""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from recording_helpers import write_recording
from rigctl.analysis import restarts
from rigctl.errors import InputError
from rigctl.recording import recorder, recording_reader

RATE = 100.0
#: (kind, label, first row, end row) of each segment; the restart at 2.5 s
SEGS = [(b"warmup", b"warm-up", 0, 100), (b"orientation", b"x up", 100, 200),
        (b"orientation", b"y up", 300, 400)]
RESTART_S = 2.5


def _columns(group: str, rows: dict[str, list]) -> dict[str, np.ndarray]:
    return {k: np.asarray(v, dtype=recorder.LAYOUT[group][k][1]) for k, v in rows.items()}


def _recording(path):
    n = 400
    write_recording(path, RATE, angular_rate=np.zeros((n, 3)), specific_force=np.tile([0, 0, 9.8], (n, 1)),
                    temperature=np.full(n, 25.0))
    m = len(SEGS)
    seg = _columns("segments", {
        "kind": [s[0] for s in SEGS], "label": [s[1] for s in SEGS], "step": list(range(m)),
        "first_sample": [s[2] for s in SEGS], "last_sample": [s[3] for s in SEGS],
        "t_start": [s[2] / RATE for s in SEGS], "t_end": [(s[3] - 1) / RATE for s in SEGS],
        "settle_time": [0.0] * m, "commanded_angle": [[0.0] * 3] * m, "commanded_rate": [[0.0] * 3] * m,
        "measured_angle": [[0.0] * 3] * m, "measured_rate": [[0.0] * 3] * m, "status": [b"complete"] * m})
    ev = _columns("events", {"time": [0.5, RESTART_S], "kind": [b"info", b"device-restart"],
                             "message": [b"started", b"IMU restarted (device time began again: power lost)"]})
    with h5py.File(path, "r+") as f:
        for group, cols in (("segments", seg), ("events", ev)):
            for k, v in cols.items():
                f.create_dataset(f"{group}/{k}", data=v).attrs["units"] = recorder.LAYOUT[group][k][2]
    return path


@pytest.fixture
def opened(monkeypatch):
    """The paths the reader opened, in order (the real opening still runs)."""
    seen: list = []
    real = recording_reader._open_h5

    def counting(p):
        seen.append(p)
        return real(p)
    monkeypatch.setattr(recording_reader, "_open_h5", counting)
    return seen


def test_restart_notes_opens_the_recording_once(tmp_path, opened):
    path = _recording(tmp_path / "rec.h5")
    notes = restarts.restart_notes(path)
    assert len(opened) == 1, opened
    # the sides from the table written above: complete orientation windows ending before /
    # starting after the event
    before = [f"step {i + 1} ({s[1].decode()})" for i, s in enumerate(SEGS)
              if s[0] == b"orientation" and (s[3] - 1) / RATE <= RESTART_S]
    after = [f"step {i + 1} ({s[1].decode()})" for i, s in enumerate(SEGS)
             if s[0] == b"orientation" and s[2] / RATE >= RESTART_S]
    assert notes == [{"time_s": RESTART_S, "event": "IMU restarted (device time began again: power lost)",
                      "before": before, "after": after}]


def test_the_events_are_still_checked_in_that_one_opening(tmp_path, opened):
    """/events shorter in one dataset (a damaged file): one InputError naming /events, as when the
    events were read in an opening of their own."""
    path = _recording(tmp_path / "rec.h5")
    with h5py.File(path, "r+") as f:
        msg = f["events/message"][()]
        del f["events/message"]
        f.create_dataset("events/message", data=msg[:1])
    with pytest.raises(InputError, match=r"/events differ in length"):
        restarts.restart_notes(path)
    assert len(opened) == 1
