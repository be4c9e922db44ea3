"""Time and data-volume estimates for a compiled plan, before anything moves."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..config.config import RigConfig
from .procedure import Step

#: Bytes per IMU sample and per table-state row in the recording (docs/data-format.md).
IMU_ROW_BYTES = 8 + 8 + 24 + 24 + 8
TABLE_ROW_BYTES = 8 + 24 + 24 + 8


def move_time(distance: float, vmax: float, amax: float) -> float:
    """Trapezoidal (or triangular) move time from rest to rest, s."""
    d = abs(distance)
    if d <= vmax * vmax / amax:
        return 2.0 * math.sqrt(d / amax)
    return d / vmax + vmax / amax


@dataclass(frozen=True)
class StepEstimate:
    step: Step
    motion_s: float
    total_s: float


def estimate(steps: list[Step], cfg: RigConfig) -> list[StepEstimate]:
    """Per-step duration: motion (trapezoid moves / rate ramps), settle hold, discard, sample."""
    out = []
    angles = np.zeros(3)
    rates = np.zeros(3)
    vmax, amax = cfg.limits.rate, cfg.limits.accel
    for s in steps:
        if not s.is_motion or s.kind in ("chamber-set", "chamber-ramp"):
            out.append(StepEstimate(s, 0.0, 0.0))
            continue
        d = np.pi - np.mod(np.pi - (s.angles - angles), 2 * np.pi)
        target_rates = np.nan_to_num(s.rates, nan=0.0)
        stop = np.abs(rates) / amax
        motion = max(float(stop[i]) + move_time(d[i], vmax[i], amax[i]) for i in range(3))
        motion += float(np.max(np.abs(target_rates) / amax))
        total = motion + s.settle.hold_s + s.discard_s + s.sample_s
        out.append(StepEstimate(s, motion, total))
        angles, rates = s.angles, target_rates
    return out


def data_volume_bytes(total_s: float, cfg: RigConfig) -> float:
    """Recording size for ``total_s`` seconds of run (IMU at its rate, table polls)."""
    return total_s * (cfg.imu_rate_hz * IMU_ROW_BYTES + 2.0 * TABLE_ROW_BYTES)
