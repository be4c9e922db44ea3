"""`rigctl batch` reports a recording it cannot analyse with the line `rigctl calibrate` would
print, not a Python class name ('FAILED: InputError: ...')."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from recording_helpers import write_recording
from rigctl.analysis import batch as B


def test_input_error_is_the_commands_line(tmp_path: Path) -> None:
    rec = write_recording(tmp_path / "r.h5", 100.0, angular_rate=np.zeros((500, 3)),
                          specific_force=np.zeros((500, 3)))
    r = B.analyse_one(str(rec))
    assert not r["ok"] and r["error"].startswith(f"{rec}: "), r["error"]
    assert "InputError" not in r["error"]
