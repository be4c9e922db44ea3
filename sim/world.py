"""The in-process emulated rig: one physics time base for the table, the IMU and the pulses.

The world advances lazily: whenever a device is read or commanded it first catches up to the
clock's current time, generating every IMU sample (and the table motion on the same grid)
in vectorised blocks. With a virtual clock a 30-minute procedure runs in seconds.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rigctl import schema as S
from rigctl.config import RigConfig
from rigctl.devices import Clock, ImuBlock, Pulses, TableState
from rigctl.frames import body_references
from rigctl.yamlio import LocDict

from .imu import build_declared_imu
from .table import OFF, POSITION, RATE, ServoParams, SimTurntable

#: Largest block generated in one call, samples (bounds memory on long sleeps).
MAX_BLOCK = 1 << 18


def _servos(o: LocDict) -> list[ServoParams]:
    S.check_keys(o, ("natural_hz", "damping", "in_position_window_deg", "at_rate_window_dps",
                     "dwell_s", "encoder_lsb_deg"), "'table.sim'")
    wn = S.number_list(o, "natural_hz", [4.0, 5.0, 6.0], length=3)
    return [ServoParams(natural_hz=wn[i], damping=S.get_number(o, "damping", 0.6, minimum=0.05, maximum=2),
                        in_position_window=math.radians(S.get_number(o, "in_position_window_deg", 0.002, minimum=0)),
                        at_rate_window=math.radians(S.get_number(o, "at_rate_window_dps", 0.01, minimum=0)),
                        dwell_s=S.get_number(o, "dwell_s", 0.2, minimum=0),
                        encoder_lsb=math.radians(S.get_number(o, "encoder_lsb_deg", 1e-5, minimum=0)))
            for i in range(3)]


class SimWorld:
    """Table + IMU physics on the IMU's sample grid (sample k at time k / rate_hz)."""

    def __init__(self, cfg: RigConfig, clock: Clock) -> None:
        self.cfg, self.clock = cfg, clock
        self.rate_hz = cfg.imu_rate_hz
        self.dt = 1.0 / self.rate_hz
        rng = np.random.default_rng(cfg.seed)
        t_opts = cfg.table.options.get("sim") or LocDict()
        t_opts = S.require_mapping(t_opts, "'table.sim'", cfg.table.options, "sim")
        continuous = [bool(np.isinf(cfg.limits.angle_min[i])) for i in range(3)]
        self.table = SimTurntable(_servos(t_opts), cfg.limits.rate, cfg.limits.accel, continuous,
                                  self.dt, rng)
        i_opts = cfg.imu.options.get("sim") or LocDict()
        i_opts = S.require_mapping(i_opts, "'imu.sim'", cfg.imu.options, "sim")
        self.imu_model = build_declared_imu(i_opts, self.rate_hz, cfg.seed)
        self.k = 0  # next sample index
        self._blocks: list[ImuBlock] = []
        self._last_w = np.zeros(3)

    def advance(self) -> None:
        """Generate every sample with time <= clock.now()."""
        k_end = int(math.floor(self.clock.now() * self.rate_hz + 1e-9)) + 1
        while self.k < k_end:
            n = min(k_end - self.k, MAX_BLOCK)
            idx = np.arange(self.k, self.k + n)
            t = idx * self.dt
            ang, rates, _acc = self.table.advance(t)
            f_b, w_b = body_references(ang, rates, self.cfg.latitude, self.cfg.height_m,
                                       self.cfg.gravity)
            f, w, temp = self.imu_model.apply(t, f_b, w_b)
            self._blocks.append(ImuBlock(t, idx.astype(np.uint64), f, w, temp))
            self.k += n

    def take_imu(self) -> ImuBlock:
        self.advance()
        blocks, self._blocks = self._blocks, []
        if not blocks:
            return ImuBlock.empty()
        if len(blocks) == 1:
            return blocks[0]
        return ImuBlock(*(np.concatenate([getattr(b, f) for b in blocks])
                          for f in ("time", "counter", "specific_force", "angular_rate", "temperature")))

    def truth(self) -> dict[str, Any]:
        return {"imu": self.imu_model.truth(), "seed": self.cfg.seed,
                "site": {"latitude_rad": self.cfg.latitude, "height_m": self.cfg.height_m,
                         "gravity_m_s2": self.cfg.gravity}}


class SimTableDevice:
    """Turntable protocol over the in-process world."""

    def __init__(self, world: SimWorld) -> None:
        self.world = world

    def _now(self) -> float:
        self.world.advance()
        return self.world.k * self.world.dt - self.world.dt if self.world.k else 0.0

    def move(self, angles: NDArray[np.float64]) -> None:
        self.check_value(angles, None)
        self.world.table.command(self._now(), [POSITION] * 3, np.asarray(angles, float))

    def set_rate(self, rates: NDArray[np.float64]) -> None:
        rates = np.asarray(rates, float)
        self.check_value(None, rates)
        t = self._now()
        for ax, r in zip(self.world.table.axes, rates):
            if not math.isnan(r):
                ax.command(t, RATE, float(r))

    def stop(self) -> None:
        self.world.table.command(self._now(), [OFF] * 3, np.zeros(3))

    def read(self) -> TableState:
        t = self._now()
        ang, rate, status = self.world.table.measured(t)
        return TableState(time=t, angle=ang, rate=rate, status=status)

    def check_value(self, angles: NDArray | None, rates: NDArray | None) -> None:
        self.world.cfg.limits.check(angles, rates)


class SimImuDevice:
    def __init__(self, world: SimWorld) -> None:
        self.world = world

    def read(self) -> ImuBlock:
        return self.world.take_imu()


class NoPulses:
    """A pulse source that never fires (rig without a pulse input)."""

    def read(self) -> Pulses:
        return Pulses(np.empty(0), source="none")
