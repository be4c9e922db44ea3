"""``rigctl thermal`` (the static fit of an imported record) across an IMU restart: NOT TRUSTWORTHY,
naming the poses and windows on each side, the same lines as ``rigctl calibrate``'s chamber path
(rigctl.analysis.restarts).

A real record: the CATS tag held still in three poses for 74.5 h (tests/data/cats-tag-thermal,
AGPL-3.0; 60-s rows), imported with its pose column as the recording's sections
(tests/cats_support.py), fitted with 60-min windows and no closed loop (~4 s of CPU each). The
restart is put in the middle of the second pose, in the real HDF5 file, in the two ways a record
can carry one: a ``device-restart`` event (as the engine records it), or a time base that begins
again behind its last stamp (the device time restarted from 0: a power loss, as the Xsens
decoder's ``device_restarts`` reads it). The control: the time base jumping *forward* by an hour
(a gap, or a reconnect's reconfiguration -- the decoder's ``time_restarts`` counts those too) is
no restart.

The expected sides come from numpy here: per pose section (cut at the restart), 60-row windows
from its first row, a last one kept with at least 30 rows (half a window).

Before: the static path never looked for restarts (no ``trustworthy`` / ``device_restarts`` in
its result), and a time base begun again was cut into windows as if it ran on.
"""
from __future__ import annotations

import shutil

import h5py
import numpy as np
import pytest

import cats_support as cats
from rigctl.analysis.thermal_static import format_text, static_fit

WINDOW_ROWS = 60   # --window-s 3600 on 60-s rows
MIN_ROWS = 30      # half a window


@pytest.fixture(scope="module")
def record(ref_data, tmp_path_factory):
    """The imported record (sections = poses), its pose per row, and the restart row: the middle
    of the second pose."""
    rows = cats.rows(ref_data)
    d = tmp_path_factory.mktemp("thermal_static_restart")
    rec = cats.import_record(ref_data, d / "marked.h5", sections=True)
    pose = np.array([r["pose"] for r in rows])
    second = np.flatnonzero(pose == cats.POSES[1])
    return rec, pose, int(second[second.size // 2] + 7)   # not on a window edge of its pose


def _windows(n_rows: int) -> int:
    full, rest = divmod(n_rows, WINDOW_ROWS)
    return full + (rest >= MIN_ROWS)


def _expected_sides(pose: np.ndarray, k: int) -> tuple[list[str], list[str]]:
    """numpy: each pose's windows on each side of row ``k`` (a pose's section is cut there)."""
    before, after = [], []
    for p in cats.POSES:
        idx = np.flatnonzero(pose == p)
        nb, na = _windows(int((idx < k).sum())), _windows(int((idx >= k).sum()))
        if nb:
            before.append(f"{p} ({nb} windows)")
        if na:
            after.append(f"{p} ({na} windows)")
    return before, after


def _copy(rec, tmp_path, name):
    out = tmp_path / name
    shutil.copy(rec, out)
    return out


def _fit(path):
    r = static_fit(path, window_s=3600.0, loop=False)
    return r, format_text(r)


def test_a_device_restart_event_makes_the_static_result_not_trustworthy(record, tmp_path):
    rec, pose, k = record
    path = _copy(rec, tmp_path, "event.h5")
    with h5py.File(path, "r+") as f:
        t_k = float(f["imu/time"][k])
        ev = f["events"]
        n = ev["time"].shape[0]
        for key in ev:
            ev[key].resize((n + 1, *ev[key].shape[1:]))
        ev["time"][n] = t_k - 1.0      # power back between rows k - 1 and k
        ev["kind"][n] = b"device-restart"
        ev["message"][n] = b"IMU restarted (device time began again: power lost) between steps"
        for key in ev:
            if key not in ("time", "kind", "message"):
                ev[key][n] = ev[key][n - 1]
    r, text = _fit(path)
    before, after = _expected_sides(pose, k)
    assert r["trustworthy"] is False
    (note,) = r["device_restarts"]
    assert (note["before"], note["after"]) == (before, after), note
    assert note["seen"] == "device-restart" and abs(note["time_s"] - (t_k - 1.0)) < 1e-9
    assert sum(int(x.rsplit("(", 1)[1].split()[0]) for x in before + after) == r["sensors"]["accel"]["windows"]
    assert f"STATUS: NOT TRUSTWORTHY: IMU restarted at t = {t_k - 1.0:.1f} s (device-restart: power lost)" in text
    assert "temperature dependence" in r["reasons"][0] and f"({', '.join(before)}; IMU " in r["reasons"][0]


def test_a_time_base_begun_again_is_a_restart_and_no_window_spans_it(record, tmp_path):
    rec, pose, k = record
    path = _copy(rec, tmp_path, "timebase.h5")
    with h5py.File(path, "r+") as f:
        t = f["imu/time"][()]
        f["imu/time"][k:] = t[k:] - t[k]          # the device time began again from 0
        t_new = f["imu/time"][()]
    r, text = _fit(path)
    before, after = _expected_sides(pose, k)
    assert r["trustworthy"] is False
    (note,) = r["device_restarts"]
    assert (note["row"], note["seen"]) == (k, "time base began again"), note
    assert (note["before"], note["after"]) == (before, after), note
    assert f"IMU restarted at row {k} of /imu (/imu/time {t_new[k - 1]:.6g} s -> 0 s) (time base began again: " \
           "power lost)" in text
    assert text.rstrip().splitlines()[-1].startswith("STATUS: NOT TRUSTWORTHY: IMU restarted at row ")


def test_a_time_base_jumping_forward_is_no_restart(record, tmp_path):
    """The control: the same record with its time an hour ahead from row k on (a gap) -- no
    restart, the windows of the uncut poses, nothing said of restarts."""
    rec, pose, k = record
    path = _copy(rec, tmp_path, "forward.h5")
    with h5py.File(path, "r+") as f:
        f["imu/time"][k:] = f["imu/time"][k:] + 3600.0
    r, text = _fit(path)
    assert r["device_restarts"] == [] and r["reasons"] == []
    assert "NOT TRUSTWORTHY" not in text and "restarted" not in text
    # no pose cut: each pose's windows as numpy cuts the whole pose (the jump is one window long)
    assert r["sensors"]["accel"]["windows"] == sum(_windows(int((pose == p).sum())) for p in cats.POSES)
