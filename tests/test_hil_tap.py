"""The emulated hardware's IMU stream carries each world sample once, in order: the physics
loop's trim of the tap (:meth:`rigctl.sim.hardware.Hardware._trim_tap`) never takes the samples
of a batch the stream thread is encoding.

Found on the HIL recordings (CI of 07702e9, tests/test_hil_runs.py): runs of 30-180 consecutive
frames carrying one and the same sample, several per 24-position run; one inside a 5 s window
moved its mean by 9 sigma of white noise. The servers raised their frame count before the
encoder read the samples; the loop, reading that count without their lock, trimmed the tap up to
it, and the tap gave every frame of the batch the first sample it still had."""
from __future__ import annotations

import time

import numpy as np
import pytest

from rigctl.sim.hardware import start_hardware

from hil_support import sim_config, wait_until


@pytest.mark.parametrize("protocol", ["xsens", "frame"])
def test_a_batch_being_encoded_keeps_its_samples(tmp_path, protocol):
    """The loop's trim run at the worst instant -- inside the encoder, just before it reads the
    batch's samples (as the physics thread may, concurrently) -- must not take them: every frame
    gets its own world sample (white noise: no two consecutive frames alike) and none asks the
    tap for a sample no longer buffered."""
    cfg, _ = sim_config(tmp_path)
    with start_hardware(cfg, 20.0, link_dir=tmp_path / "ports", imu_protocol=protocol) as hw:
        srv = hw.imu_server
        if srv.state != "measurement":          # Xsens: as after GoToMeasurement
            with srv._lock:
                srv._enter_measurement()
        wait_until(lambda: srv.frames_sent > 20, 30.0, "the first frames")
        hw.pause_physics(60.0)                  # the loop stands still: only this test steps now
        time.sleep(0.3)                         # (its iteration under way ends)
        sent0, clamped0 = srv.frames_sent, hw.tap.clamped
        got: list[tuple[np.ndarray, np.ndarray]] = []
        source = srv.source

        def source_racing_the_trim(t: np.ndarray) -> dict:
            hw._trim_tap(0)                     # the physics loop's trim, at the worst instant
            out = source(t)
            got.append((np.array(t), np.array(out["acceleration"])))
            return out

        srv.source = source_racing_the_trim
        with hw.lock:                           # the world one step on, as the loop does
            hw.world_clock.cap = hw.table._t() + 2.0
            hw.world.advance()
            hw.tap.pull()
            until = hw.table._t()
        n = srv.step(until)
        srv.source = source
    assert n >= 50 and srv.frames_sent == sent0 + n
    t = np.concatenate([x for x, _ in got])
    acc = np.concatenate([a for _, a in got])
    assert len(t) == n and np.all(np.diff(t) > 0)
    assert hw.tap.clamped == clamped0, f"{hw.tap.clamped - clamped0} of {n} frames got a sample no longer buffered"
    alike = np.flatnonzero(np.all(acc[1:] == acc[:-1], axis=1))
    assert alike.size == 0, f"{alike.size} of {n - 1} consecutive frames carry the same sample"
