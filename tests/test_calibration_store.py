"""Storing a calibration's results in its recording (rigctl.recording.segment_builder.
store_calibration_results, used by rigctl calibrate and the thermal calibration): stored in a
closed recording, refused with one line in a recording a run is still writing."""
from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from recording_helpers import _group, write_recording
from rigctl.recording import recorder
from rigctl.recording.segment_builder import store_calibration_results


def _recording(path, status):
    p = write_recording(path, 100.0, status=status, angular_rate=np.zeros((10, 3)),
                        specific_force=np.zeros((10, 3)))
    with h5py.File(p, "a") as f:  # an empty /segments table: what a calibration's opener needs
        _group(f, "segments", {k: np.zeros((0, *shape), dtype=dt)
                               for k, (shape, dt, _) in recorder.LAYOUT["segments"].items()})
    return p


@pytest.mark.parametrize("status", ["complete", "interrupted", "failed"])
def test_stored_in_a_closed_recording(tmp_path, status):
    p = _recording(tmp_path / "r.h5", status)
    assert store_calibration_results(p, "thermal", {"x_m_s2": 1.5}, {"v": (np.arange(3.0), "m/s^2")},
                                     schema_version=3) is None
    with h5py.File(p, "r") as f:
        g = f["results/thermal"]
        assert json.loads(g.attrs["json"]) == {"x_m_s2": 1.5} and g.attrs["schema_version"] == 3
        assert g["v"][()].tolist() == [0.0, 1.0, 2.0] and g["v"].attrs["units"] == "m/s^2"


def test_not_stored_while_a_run_writes_the_recording(tmp_path):
    p = _recording(tmp_path / "r.h5", "running")
    line = store_calibration_results(p, "calibration", {"x": 1})
    assert line == "not stored in the recording: it is still being written (status running)"
    with h5py.File(p, "r") as f:
        assert "results" not in f
