"""The ``sync`` solve step: `rigctl run procedures/taps.yaml --config configs/sim-taps.yaml` ends
with /results/sync in the recording, the same as `rigctl sync` gives, and the IMU clock drift it
finds is the emulated one (read from the recording's /truth, not from the pipeline)."""
from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers import run_rigctl

from rigctl.cli import main


@pytest.fixture(scope="module")
def tap_run(tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("runs")
    r = run_rigctl("run", "procedures/taps.yaml", "--config", "configs/sim-taps.yaml", "--out", str(out))
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    return next(out.glob("*-taps")) / "recording.h5", r.stdout


def test_the_procedure_ends_with_results_sync(tap_run) -> None:
    rec, stdout = tap_run
    lines = stdout.splitlines()
    assert lines[-1] == f"recording: {rec}"
    assert "sync: timing subsample, axis az; wrote /results/sync" in lines
    with h5py.File(rec, "r") as f:
        g = f["results/sync"]
        s = json.loads(g.attrs["json"])
        counter = f["imu/counter"][()]
        ref = g["reference_time"][()]
        pulses = f["pulses/time"][()]
        truth = json.loads(f["truth"].attrs["params_json"])
        tap_row, pulse_time, inlier = g["tap_row"][()], g["pulse_time"][()], g["inlier"][()]
    assert ref.shape == counter.shape and np.all(np.diff(ref) > 0)
    assert s["n_pulses"] == pulses.size and s["n_inliers"] >= 10
    # the emulated IMU clock runs 85 ppm slow (configs/sim-taps.yaml, profile mti_class)
    true_ppm = truth["imu"]["effects"]["clock"]["drift_ppm"]
    assert true_ppm == 85.0
    assert abs(s["drift_ppm"] - true_ppm) <= s["drift_ci95_ppm"], s
    # independent of the pipeline: a line through (sample time of the detection row, pulse time)
    # of the matched pairs; its slope agrees with the pipeline's within the two uncertainties
    # (the rows are quantised to 10 ms: uniform error, sd 10 ms / sqrt(12) per tap)
    ok = inlier.astype(bool)
    x = counter[tap_row[ok]] / 100.0
    slope = np.polyfit(x, pulse_time[ok], 1)[0]
    sd_slope = 0.01 / np.sqrt(12) / (np.std(x) * np.sqrt(x.size))
    plain_ppm = (slope - 1.0) * 1e6
    assert abs(plain_ppm - s["drift_ppm"]) < 3 * np.hypot(sd_slope * 1e6, s["drift_sigma_ppm"]), \
        (plain_ppm, sd_slope * 1e6, s)


def test_the_solve_step_and_the_command_agree(tap_run, tmp_path: Path, capsys) -> None:
    rec, _ = tap_run
    with h5py.File(rec, "r") as f:
        hook = json.loads(f["results/sync"].attrs["json"])
        hook_ref = f["results/sync/reference_time"][()]
    copy = tmp_path / "again.h5"
    copy.write_bytes(rec.read_bytes())
    assert main(["sync", str(copy)]) == 0
    assert f"wrote /results/sync to {copy}" in capsys.readouterr().out
    with h5py.File(copy, "r") as f:
        cli = json.loads(f["results/sync"].attrs["json"])
        np.testing.assert_array_equal(f["results/sync/reference_time"][()], hook_ref)
    hook.pop("options"), cli.pop("options")
    assert cli == hook


def test_a_recording_without_pulses_is_a_warning(tmp_path: Path) -> None:
    """configs/sim.yaml has no tap hammer: the run completes (exit 0) and says why no sync."""
    r = run_rigctl("run", "procedures/taps.yaml", "-p", "warmup=5 s", "-p", "window=20 s",
                   "--out", str(tmp_path))
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    rec = next(tmp_path.glob("*-taps")) / "recording.h5"
    assert f"warning: sync: {rec}: 0 pulses recorded" in r.stdout + r.stderr
    with h5py.File(rec, "r") as f:
        assert "results" not in f or "sync" not in f["results"]
