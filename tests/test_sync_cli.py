"""`rigctl sync` on real HDF5 recordings written with plain h5py (schema_version 1 layout)."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import h5py
import numpy as np
import pytest

import recording_helpers
from rigctl import cli
from rigctl.commands import sync_cmd
from rigctl.analysis.sync import GPS_WEEK_S
from rigctl.sim import taps

RATE = 100.0


@pytest.fixture(scope="module")
def session() -> taps.TapSession:
    sched = taps.ScheduleParams((30.0, 330.0, 630.0, 900.0), 10, (1.0, 3.0))
    params = taps.TapParams(response="second_order", jitter_s=2e-4, missed_count=1,
                            spurious_spikes=2)
    return taps.simulate_taps(RATE, 960.0, sched, params,
                              taps.ClockParams(offset_s=0.2, drift_ppm=60.0),
                              random_dropouts=1, dropout_length=32, seed=11)


def write_recording(path: Path, s: taps.TapSession, *, pulses: bool = True) -> None:
    """A tap session as a minimal recording (tests/recording_helpers.py)."""
    n, k = s.counter.size, s.pulse_time.size
    gps0 = 33000.0
    marks = {"time": s.pulse_time, "gps_week": np.full(k, 2300, dtype=np.int32),
             "gps_seconds": s.pulse_time + gps0, "source": np.full(k, b"sim", dtype="S16")}
    recording_helpers.write_recording(path, RATE, counter=s.counter, specific_force=s.specific_force,
                                      angular_rate=np.zeros((n, 3)), temperature=np.full(n, 25.0),
                                      pulses=marks if pulses else None, truth_json=s.truth.params_json())


def _args(path: Path, *extra: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="rigctl")
    sync_cmd.register(parser.add_subparsers(dest="command", required=True))
    return parser.parse_args(["sync", str(path), *extra])


def test_sync_writes_results_and_reference_time(tmp_path: Path, session, capsys) -> None:
    rec = tmp_path / "run.h5"
    write_recording(rec, session)
    args = _args(rec)
    assert args.func is sync_cmd.run
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "drift" in out and "ppm" in out and "counter gap: 32 samples" in out
    with h5py.File(rec, "r") as f:
        g = f["results/sync"]
        assert g.attrs["schema_version"] == 1 and "T" in g.attrs["created_utc"]
        summary = json.loads(g.attrs["json"])
        ref = g["reference_time"][()]
        assert g["reference_time"].attrs["units"] == "s"
        assert g["pulse_time"].shape == g["tap_time_imu"].shape
    assert summary["timing"] == "subsample"
    assert summary["n_taps_without_pulse"] == 3  # one missed pulse + two spurious spikes
    assert summary["n_pulses_without_tap"] == 0
    assert abs(summary["drift_ppm"] - 60.0) < 3 * summary["drift_sigma_ppm"] + 0.05
    assert summary["counter_gaps"][0]["n_samples"] == 32
    true_ref = session.truth.time_of_counter(session.counter.astype(float))
    assert ref.shape == (session.counter.size,)
    assert np.max(np.abs(ref - true_ref)) < 0.5e-3


def test_sync_plots(tmp_path: Path, session) -> None:
    pytest.importorskip("matplotlib")  # optional extra rigctl[report]
    rec = tmp_path / "run.h5"
    write_recording(rec, session)
    assert cli.main(["sync", str(rec), "--plot-dir", str(tmp_path / "plots")]) == 0
    for name in ("sync_hist.png", "sync_residual.png"):
        assert (tmp_path / "plots" / name).stat().st_size > 1000


def test_sync_rerun_replaces_results_and_gps_timescale(tmp_path: Path, session) -> None:
    rec = tmp_path / "run.h5"
    write_recording(rec, session)
    assert cli.main(["sync", str(rec)]) == 0
    assert cli.main(["sync", str(rec), "--timescale", "gps", "--response", "none"]) == 0
    with h5py.File(rec, "r") as f:
        summary = json.loads(f["results/sync"].attrs["json"])
        assert list(f["results"].keys()) == ["sync"]
    assert summary["timing"] == "half_sample"
    gps_offset = 2300 * GPS_WEEK_S + 33000.0
    assert summary["offset_s"] == pytest.approx(0.2 + gps_offset, abs=5e-3)
    assert summary["options"]["timescale"] == "gps"


def test_sync_invalid_inputs_exit_2(tmp_path: Path, session, capsys) -> None:
    missing = tmp_path / "nope.h5"
    assert cli.main(["sync", str(missing)]) == 2
    assert "nope.h5: no such file" in capsys.readouterr().err
    junk = tmp_path / "junk.h5"
    junk.write_text("not hdf5")
    assert cli.main(["sync", str(junk)]) == 2
    assert "junk.h5: not an HDF5 file" in capsys.readouterr().err
    nopulse = tmp_path / "nopulse.h5"
    write_recording(nopulse, session, pulses=False)
    assert cli.main(["sync", str(nopulse)]) == 2
    err = capsys.readouterr().err
    assert "nopulse.h5" in err and "/pulses/time" in err
    with h5py.File(nopulse, "r") as f:
        assert "results" not in f  # nothing written on invalid input


def test_sync_fails_cleanly_without_taps(tmp_path: Path, capsys) -> None:
    s = taps.simulate_taps(RATE, 60.0, taps.ScheduleParams((10.0,), 10, (1, 2)),
                           taps.TapParams(amplitude_median_m_s2=1e-3), seed=2)  # taps in noise
    rec = tmp_path / "quiet.h5"
    write_recording(rec, s)
    assert cli.main(["sync", str(rec)]) == 1
    assert "taps detected" in capsys.readouterr().err


def test_sync_tap_axis_in_the_one_spelling(tmp_path: Path, session, capsys) -> None:
    """`--axis` takes the axis spelling of every command (az), still reads the bare z and an old
    alias to the same result, and refuses a gyro axis in one line (taps are in the specific force)."""
    rec = tmp_path / "run.h5"
    write_recording(rec, session)
    offsets = []
    for given in ("az", "z", "ACC_Z"):
        assert cli.main(["sync", str(rec), "--axis", given]) == 0
        assert "axis az" in capsys.readouterr().out
        with h5py.File(rec, "r") as f:
            summary = json.loads(f["results/sync"].attrs["json"])
        assert summary["options"]["axis"] == "az"
        offsets.append(summary["offset_s"])
    assert offsets[0] == offsets[1] == offsets[2]
    assert cli.main(["sync", str(rec), "--axis", "gz"]) == 2
    err = capsys.readouterr().err
    assert "'gz'" in err and "ax, ay, az" in err and "Traceback" not in err
