"""The in-process emulated rig: one physics time base for the table, the IMU and the pulses.

The world advances lazily: whenever a device is read or commanded it first catches up to the
clock's current time (the true, run time), advancing the table on its own grid and generating
every IMU sample whose true time has passed, in vectorised blocks. With a virtual clock a
30-minute procedure runs in seconds.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rigctl import schema as S
from rigctl.config.config import RigConfig
from rigctl.devices import AxisStatus, Clock, DeviceFault, ImuBlock, LinkLost, NoPulses, TableState
from rigctl.frames import _earth_rate_cached, _normal_gravity_cached, body_references, gimbal_rate_body
from rigctl.settings import Settings, per_axis, section, yaml_keys
from rigctl.yamlio import LocDict

from . import declared_kernels
from .faults import FaultInjector
from .effects import table_body_references
from .imu import DeclaredImuModel, build_imu_model
from .error_model import SampleGrid
from .tap_rig import TRUTH_TABLES, SimPulses, SimTapOperator, TapRigSettings
from .table import OFF, POSITION, RATE, ServoParams, SimTurntable

#: Largest block generated in one call, samples (bounds memory on long sleeps).
MAX_BLOCK = 1 << 18

#: On a clock that runs with the wall (scaled, real) the world catches up in pieces and gives
#: up after this much wall time in one call: the rest of the clock's lead is taken back
#: (``clock.slip_to``), so rig time runs as fast as the host computes. Without it an emulator asked
#: for more than the host can compute (500x at 100 Hz on a loaded 2-core host: ~120x) fell
#: further behind at every call -- each catch-up took longer than the rig time it covered, so
#: the next one had more to do -- and one poll ended hours of rig time later (a 30 s warm-up:
#: 7.5 min of wall time, 560 MB of samples, SIGTERM noticed only at the end of the poll). 0.05 s:
#: SIGTERM to the recording closed in 0.2-0.35 s at 10000x, load 12 (0.1 s: 1.7 s), s.
ADVANCE_BUDGET_WALL_S = 0.05
#: ... in pieces of at most this much wall time x speed of rig time (at least 1 s, at most 1024
#: IMU samples: 8192 took 0.3-1.5 s at load 20 on 2 cores, and a poll reads three devices), s
ADVANCE_PIECE_WALL_S = 0.02


@dataclass(frozen=True, kw_only=True)
class TableSimSettings(Settings):
    """``table.sim``: the emulated table's servos, per axis (a number for all axes, or
    [outer, middle, inner]); docs/emulator.md section 6."""

    natural_hz: tuple[float, ...] = per_axis((4.0, 5.0, 6.0), minimum=0.1)
    damping: tuple[float, ...] = per_axis((0.6,) * 3, minimum=0.05, maximum=2)
    in_position_window_deg: tuple[float, ...] = per_axis((0.002,) * 3, minimum=0)
    at_rate_window_dps: tuple[float, ...] = per_axis((0.01,) * 3, minimum=0)
    dwell_s: tuple[float, ...] = per_axis((0.2,) * 3, minimum=0)
    encoder_lsb_deg: tuple[float, ...] = per_axis((1e-5,) * 3, minimum=0)
    encoder_noise_deg: tuple[float, ...] = per_axis((0.0,) * 3, minimum=0)
    rate_ripple_per_rev: tuple[float, ...] = per_axis((0.0,) * 3, minimum=0, maximum=0.1)
    rate_ripple_per_rev_phase_deg: tuple[float, ...] = per_axis((0.0,) * 3)
    rate_ripple_fraction: tuple[float, ...] = per_axis((0.0,) * 3, minimum=0, maximum=0.1)
    rate_ripple_hz: tuple[float, ...] = per_axis((0.0,) * 3, minimum=0)
    rate_ripple_phase_deg: tuple[float, ...] = per_axis((0.0,) * 3)
    wobble_rad: tuple[float, ...] = per_axis((0.0,) * 3, minimum=0, maximum=0.01)
    wobble_harmonic: tuple[int, ...] = per_axis((2,) * 3, minimum=1, maximum=100, integer=True)
    wobble_phase_deg: tuple[float, ...] = per_axis((0.0,) * 3)
    jerk_dps3: tuple[float, ...] = per_axis((math.inf,) * 3, minimum=1e-3)

    def servos(self) -> list[ServoParams]:
        """The three axes' servo parameters, SI (rad, rad/s)."""
        r = math.radians
        return [ServoParams(natural_hz=self.natural_hz[i], damping=self.damping[i],
                            in_position_window=r(self.in_position_window_deg[i]),
                            at_rate_window=r(self.at_rate_window_dps[i]), dwell_s=self.dwell_s[i],
                            encoder_lsb=r(self.encoder_lsb_deg[i]), encoder_noise=r(self.encoder_noise_deg[i]),
                            ripple_per_rev=self.rate_ripple_per_rev[i],
                            ripple_per_rev_phase=r(self.rate_ripple_per_rev_phase_deg[i]),
                            ripple_fraction=self.rate_ripple_fraction[i], ripple_hz=self.rate_ripple_hz[i],
                            ripple_phase=r(self.rate_ripple_phase_deg[i]), wobble=self.wobble_rad[i],
                            wobble_harmonic=int(self.wobble_harmonic[i]),
                            wobble_phase=r(self.wobble_phase_deg[i]), jerk_max=r(self.jerk_dps3[i]))
                for i in range(3)]


#: Per-axis servo keys of ``table.sim`` (a number for all axes, or [outer, middle, inner]).
SERVO_KEYS = tuple(yaml_keys(TableSimSettings))


def _canonical(v: Any) -> Any:
    """Settings with every number as a float (``20`` and ``20.0`` are the same setting)."""
    if isinstance(v, dict):
        return {str(k): _canonical(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_canonical(x) for x in v]
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return float(v)
    return v


def emulated_imu_identity(imu_sim: LocDict, seed: int) -> dict[str, str]:
    """The emulated IMU's identity: ``EMU-<profile>-<digest>`` (``declared`` without a profile).

    A unit is what stays fixed from one power-on to the next: the ``imu.sim`` settings (profile,
    overrides, declared errors), hashed (SHA-256, 8 hex digits) without the seed, which only draws
    the noise and the per-power-on parts -- two runs with other seeds are the same unit on two
    days. With ``profile: random`` the seed (``imu.sim.seed``, else the config's ``seed``) draws
    the unit itself, so it is part of the digest."""
    opts = {k: v for k, v in dict(imu_sim).items() if k != "seed"}
    profile = str(opts.get("profile") or "declared")
    if profile == "random":
        opts["seed"] = int(imu_sim.get("seed", seed))
    digest = hashlib.sha256(json.dumps(_canonical(opts), sort_keys=True, default=str).encode()).hexdigest()[:8]
    return {"device_id": f"EMU-{profile}-{digest.upper()}", "protocol": "in-process emulator"}


class SimWorld:
    """Table + IMU physics on one true (run) timescale.

    The table evolves on its own uniform grid of run time, t_j = j h (h = the IMU's internal
    sample period, 1 / (rate_hz x decimation)), so its motion, status and reported state do not
    depend on the IMU. The IMU samples that physical world at ITS sample instants: the true
    times of its clock (drift, wander, drops; :class:`rigctl.sim.error_model.SampleGrid`), the
    table being evaluated exactly at those instants (:meth:`SimTurntable.at`). A sample is
    produced once the run clock has passed its true time; its time stamp is the IMU's own,
    counter / rate_hz. Commands act at the current run time :attr:`t`.
    """

    def __init__(self, cfg: RigConfig, clock: Clock) -> None:
        self.cfg, self.clock = cfg, clock
        self.rate_hz = cfg.imu_rate_hz
        self.dt = 1.0 / self.rate_hz
        rng = np.random.default_rng(cfg.seed)
        i_opts = cfg.imu.options.get("sim") or LocDict()
        i_opts = S.require_mapping(i_opts, "'imu.sim'", cfg.imu.options, "sim")
        self.imu_model = build_imu_model(i_opts, self.rate_hz, cfg.seed)
        self.imu_identity = emulated_imu_identity(i_opts, cfg.seed)
        # the table's grid step is the IMU's internal (pre-decimation) sample period
        self.decimation = int(getattr(self.imu_model, "decimation", 1))
        self.h = self.dt / self.decimation
        servos = section(cfg.table.options, "sim", TableSimSettings, "'table.sim'").servos()
        continuous = [bool(np.isinf(cfg.limits.angle_min[i])) for i in range(3)]
        self.table = SimTurntable(servos, cfg.limits.rate, cfg.limits.accel, continuous,
                                  self.h, rng)
        self.t = 0.0  # run time the world has been advanced to (a grid time when within rounding), s
        self.k = 0  # counter of the next IMU output sample
        self._j = 0  # index of the next table grid point (time j h)
        self._pending: SampleGrid | None = None  # IMU samples drawn from its clock, not yet due
        self._blocks: list[tuple[ImuBlock, NDArray]] = []  # (block, true times of its samples)
        self.faults = FaultInjector()  # sim/faults.py: injected faults the devices obey
        #: the IMU's power cycles so far (:meth:`power_cycle_imu`): time and new turn-on biases
        self.imu_power_cycles: list[dict[str, Any]] = []
        self._cycles_drained = 0  # of them, how many the recorder has taken (drain_power_cycles)
        # the climatic chamber (sim/chamber.py) and the IMU's thermal state along it: the
        # declared IMU's temperature is the chamber's product temperature (idle at the IMU's
        # temperature_c unless chamber.sim says otherwise); a profile IMU keeps its own
        # (warm-up) temperature model
        from .chamber import ChamberPhysics, chamber_params
        from .thermal_imu import ThermalTrack
        c_opts = cfg.chamber.options.get("sim")
        cp = chamber_params(S.require_mapping(c_opts, "'chamber.sim'", cfg.chamber.options, "sim")
                            if c_opts is not None else None)
        if c_opts is None or "initial_c" not in c_opts:
            t0 = float(getattr(self.imu_model, "temperature_c", cp.initial_c))
            cp = dataclasses.replace(cp, initial_c=t0)
        self.chamber = ChamberPhysics(cp)
        self.chamber_drives_imu = isinstance(self.imu_model, DeclaredImuModel)
        th = getattr(self.imu_model, "thermal", None)
        self.thermal_track = ThermalTrack(th.hyst_width if th is not None else 2.0)
        self._track_t = -1.0
        self.operator: SimTapOperator | None = None  # emulated tap-hammer operator (pulses: sim)
        if cfg.pulses.driver == "sim":
            taps = section(cfg.pulses.options, "sim", TapRigSettings, "'pulses.sim'")
            self.operator = SimTapOperator(taps.tap_params(), taps.margin_s, taps.slot_jitter,
                                           taps.seed or cfg.seed)

    def _wobble(self, ang: NDArray, rates: NDArray, f_b: NDArray,
                w_b: NDArray) -> tuple[NDArray, NDArray]:
        """References in the wobbling body frame: C' = C (I + [d x]) gives, to first order,
        f' = f - d x f and w' = w - d x w + d' (d, d' from SimTurntable.wobble)."""
        wob = self.table.wobble(ang, rates)
        if wob is None:
            return f_b, w_b
        d, dd = wob
        return f_b - np.cross(d, f_b), w_b - np.cross(d, w_b) + dd

    def _taps(self, t: NDArray[np.float64], f: NDArray[np.float64]) -> NDArray[np.float64]:
        """True specific force ``f`` plus the scheduled taps at the true times ``t``."""
        if self.operator is not None:
            f = np.array(f, dtype=float, copy=True)
            self.operator.field.apply(t, f)
        return f

    def advance(self) -> None:
        """Bring the world to the clock's time: the table's grid up to it, and every IMU sample
        whose true time has passed (in blocks of at most MAX_BLOCK table points).

        A clock that can be set back (``slip_to``: the scaled and real clocks) is caught up to the
        time it has run to (``running_now``) in pieces; after :data:`ADVANCE_BUDGET_WALL_S` of
        wall time in one call the clock is set back to the time reached. The samples stay one unbroken series; rig time runs slower."""
        slip_to = getattr(self.clock, "slip_to", None)
        if slip_to is None:
            self._advance_to(self.clock.now())
            return
        target = max(self.clock.running_now(), self.t)
        speed = float(getattr(self.clock, "speed", 1.0))
        piece = min(max(1.0, ADVANCE_PIECE_WALL_S * speed, 16 * self.dt), 1024 * self.dt)
        wall0 = time.monotonic()
        while target - self.t > piece:
            self._advance_to(self.t + piece)
            if time.monotonic() - wall0 > ADVANCE_BUDGET_WALL_S:
                slip_to(self.t)
                return
        self._advance_to(target)

    def _advance_to(self, until: float) -> None:
        now = max(until, self.t)
        j_end = int(math.floor(now / self.h + 1e-9)) + 1  # grid points with t_j <= now
        t_grid = (j_end - 1) * self.h
        if abs(now - t_grid) <= 1e-6 * self.h:  # a clock time on the grid but for rounding
            now = max(t_grid, self.t)
        while True:
            j_stop = min(j_end, self._j + MAX_BLOCK)
            if j_stop > self._j:
                self.table.step(np.arange(self._j, j_stop) * self.h)
                self._j = j_stop
            until = now if j_stop == j_end else (j_stop - 1) * self.h
            if isinstance(self.imu_model, DeclaredImuModel):
                self._declared_until(until)
            else:
                self._model_until(until)
            self.table.forget_before(self._next_eval_time())
            if j_stop == j_end:
                break
        self.t = now

    def _thermal_at(self, t: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """The IMU's temperature (the chamber's product temperature), hysteresis state and
        temperature rate at true times ``t``."""
        T = self.chamber.history(t)
        th = getattr(self.imu_model, "thermal", None)
        if th is None or not th.active:
            return T, None, None
        ht, hp = self.chamber.grid_since(self._track_t)
        if ht.size:
            self.thermal_track.extend(ht, hp)
            self._track_t = float(ht[-1])
        H, R = self.thermal_track.at(t)
        return T, H, R

    def _next_eval_time(self) -> float:
        """Earliest time at which a future IMU sample will look at the table, s."""
        if self._pending is not None:
            return float(self._pending.t_eval[0])
        return self.k * self.dt if isinstance(self.imu_model, DeclaredImuModel) else -math.inf

    def _declared_until(self, until: float) -> None:
        """Declared model: samples on the nominal grid k / rate_hz (its clock is perfect)."""
        k_end = int(math.floor(until * self.rate_hz + 1e-9)) + 1
        while self.k < k_end:
            n = min(k_end - self.k, MAX_BLOCK)
            idx = np.arange(self.k, self.k + n)
            t = idx * self.dt
            ang, rates, _acc = self.table.at(t)
            f_b, w_b = self._body_references(ang, rates)
            f_b, w_b = self._wobble(ang, rates, f_b, w_b)
            T, H, R = self._thermal_at(t)
            f, w, temp = self.imu_model.apply(t, self._taps(t, f_b), w_b, temperature=T,
                                              hysteresis=H, temperature_rate=R)
            self._emit(t, idx.astype(np.uint64), f, w, temp, t)
            self.k += n

    def _body_references(self, ang: NDArray, rates: NDArray) -> tuple[NDArray, NDArray]:
        """:func:`rigctl.frames.body_references` at the config's site; blocks of two samples or
        more compiled (sim/declared_kernels.py: the same floats) where that is exact here."""
        site = self.__dict__.get("_refs_site")
        if site is None or site[0] is not self.cfg:  # the frozen config's site, once
            cfg = self.cfg
            site = self._refs_site = (cfg, cfg.latitude, cfg.height_m, cfg.gravity)
        _, lat, height, g = site
        if ang.shape[0] >= 2 and declared_kernels.ready(DeclaredImuModel):
            g_site = _normal_gravity_cached(lat, height) if g is None else float(g)
            return declared_kernels.body_references(ang, rates, g_site, _earth_rate_cached(lat))
        return body_references(ang, rates, lat, height, g)

    def _model_until(self, until: float) -> None:
        """Full error model: every sample whose true time (its own clock) is <= ``until``."""
        lim = until + 1e-6 * self.h
        max_out = max(1, MAX_BLOCK // self.decimation)
        while True:
            g = self._pending
            if g is None or g.t_out[-1] <= lim:
                if g is not None and g.t_out.size >= max_out:
                    self._model_block(self._take(max_out))
                    continue
                last = float(g.t_out[-1]) if g is not None else 0.0
                n = int(min(max_out, max(16.0, (lim - last) * self.rate_hz * 1.01 + 16)))
                self._extend(self.imu_model.sample_grid(n))
                continue
            m = int(np.searchsorted(g.t_out, lim, side="right"))
            if m == 0:
                return
            self._model_block(self._take(min(m, max_out)))

    def _extend(self, g: SampleGrid) -> None:
        p = self._pending
        self._pending = g if p is None else SampleGrid(
            *(np.concatenate([getattr(p, f), getattr(g, f)])
              for f in ("t_internal", "t_eval", "t_out", "counter", "keep")))

    def _take(self, m: int) -> SampleGrid:
        """The first m pending output samples (and their internal samples)."""
        p, L = self._pending, self.decimation
        assert p is not None
        head = SampleGrid(p.t_internal[: m * L], p.t_eval[: m * L], p.t_out[:m], p.counter[:m], p.keep[:m])
        rest = SampleGrid(p.t_internal[m * L:], p.t_eval[m * L:], p.t_out[m:], p.counter[m:], p.keep[m:])
        self._pending = rest if rest.t_out.size else None
        return head

    def _model_block(self, g: SampleGrid) -> None:
        ang, rates, acc = self.table.at(g.t_eval)  # the table at the IMU's (delayed) instants
        site = self.__dict__.get("_site")
        if site is None or site[0] is not self.cfg:  # the frozen config's latitude and g, once
            site = self._site = (self.cfg, self.cfg.latitude, self.cfg.gravity)
        kernels = ang.shape[0] >= 2 and declared_kernels.ready(DeclaredImuModel)  # the same floats, compiled
        refs = declared_kernels.table_body_references if kernels else table_body_references
        f_b, w_b = refs(ang, rates, site[1], site[2], **self.imu_model.table_geometry())
        f_b, w_b = self._wobble(ang, rates, f_b, w_b)
        # d/dt of the table rate at frozen angles
        w_dot = declared_kernels.gimbal_rate_body(ang, acc) if kernels else gimbal_rate_body(ang, acc)
        f_b = self._taps(g.t_eval, f_b)  # taps happen at the IMU, before its front end
        T = self._thermal_at(g.t_internal)[0] if self.chamber_drives_imu else None
        f, w, temp = self.imu_model.apply(g.t_internal, f_b, w_b, temperature=T, w_dot=w_dot)
        keep = g.keep
        counter = g.counter[keep]
        self._emit(counter.astype(np.float64) / self.rate_hz, counter, f[keep], w[keep], temp[keep],
                   g.t_out[keep])
        self.k = int(g.counter[-1]) + 1

    def _emit(self, t: NDArray, counter: NDArray, f: NDArray, w: NDArray, temp: NDArray,
              t_true: NDArray) -> None:
        if self.faults.windows:
            temp = temp + self.faults.temperature_offset(t_true)
        self._blocks.append((ImuBlock(t, counter, f, w, temp), t_true))

    def take_imu(self, advance: bool = True, true_time: bool = False) -> Any:
        """Samples generated since the last call (after catching up to the clock if ``advance``);
        with ``true_time`` the pair (block, true run time of each sample, s)."""
        if advance:
            self.advance()
        blocks, self._blocks = self._blocks, []
        if not blocks:
            out, tt = ImuBlock.empty(), np.empty(0)
        elif len(blocks) == 1:
            out, tt = blocks[0]
        else:
            out = ImuBlock(*(np.concatenate([getattr(b, f) for b, _ in blocks])
                             for f in ("time", "counter", "specific_force", "angular_rate", "temperature")))
            tt = np.concatenate([x for _, x in blocks])
        return (out, tt) if true_time else out

    def power_cycle_imu(self) -> None:
        """The IMU lost power and is back (now, run time :attr:`t`): its model draws a new
        turn-on bias (``power_cycle``: the repeatability of the declared model or of the profile's
        ``turn_on_bias`` effect), listed with its time in :attr:`imu_power_cycles` (``truth()``)."""
        g, a = self.imu_model.power_cycle()
        self.imu_power_cycles.append({"t_s": self.t, "gyro_turn_on_bias_rad_s": g.tolist(),
                                      "accel_turn_on_bias_m_s2": a.tolist()})

    def drain_power_cycles(self) -> dict[str, dict[str, NDArray]]:
        """The power cycles since the last call as rows of :data:`POWER_CYCLE_TABLE`
        ({"imu_power_cycles": {column: array}}; {} when none): the recorder's
        /truth/imu_power_cycles."""
        new = self.imu_power_cycles[self._cycles_drained:]
        self._cycles_drained += len(new)
        if not new:
            return {}
        return {"imu_power_cycles": {
            "time_s": np.array([c["t_s"] for c in new], float),
            "gyro_turn_on_bias_rad_s": np.array([c["gyro_turn_on_bias_rad_s"] for c in new], float),
            "accel_turn_on_bias_m_s2": np.array([c["accel_turn_on_bias_m_s2"] for c in new], float)}}

    def truth(self) -> dict[str, Any]:
        """Every true parameter (a dict, JSON-serialisable), with what is drawn during the run
        (:class:`RunTruth`): the IMU's power cycles (/truth/imu_power_cycles: each new turn-on
        bias and when it takes effect) and, with the tap operator, the taps (/truth/taps and
        /truth/edges). ``imu_power_cycles`` here: the cycles so far (none when the recording is
        created, so its params_json holds the first turn-on's bias only)."""
        out = {"imu": self.imu_model.truth(), "table": self.table.truth(), "seed": self.cfg.seed,
               "chamber": self.chamber.truth(), "imu_power_cycles": list(self.imu_power_cycles),
               "site": {"latitude_rad": self.cfg.latitude, "height_m": self.cfg.height_m,
                        "gravity_m_s2": self.cfg.gravity}}
        if self.operator is not None:
            out["pulses"] = self.operator.truth()
        return RunTruth(out, self, self.operator)

    def pulses(self) -> Any:
        """The rig's pulse source: the emulated receiver's input, or one that never fires."""
        return NoPulses() if self.operator is None else SimPulses(self.operator, self.clock)


#: the IMU's power cycles as a /truth table (docs/data-format.md): one row per cycle, the run
#: time of the draw (every IMU sample after it carries the new turn-on bias) and the new
#: turn-on biases (the profile model's replace the last; the declared model's add to its bias)
POWER_CYCLE_TABLE: dict[str, dict[str, tuple[tuple[int, ...], Any, str]]] = {"imu_power_cycles": {
    "time_s": ((), np.float64, "s"),
    "gyro_turn_on_bias_rad_s": ((3,), np.float64, "rad/s"),
    "accel_turn_on_bias_m_s2": ((3,), np.float64, "m/s^2")}}


class RunTruth(dict):
    """The truth dict plus the tables of truth drawn during the run, for the recorder
    (rigctl.recording.recorder: ``truth_tables`` is the layout, ``drain_truth_rows()`` the new
    rows): the world's IMU power cycles, and the tap operator's taps and edges when there is one."""

    def __init__(self, params: dict[str, Any], world: SimWorld, operator: SimTapOperator | None) -> None:
        super().__init__(params)
        self.world, self.operator = world, operator
        self.truth_tables = {**POWER_CYCLE_TABLE, **(TRUTH_TABLES if operator is not None else {})}

    def drain_truth_rows(self) -> dict[str, dict[str, NDArray]]:
        rows = self.operator.drain_truth_rows() if self.operator is not None else {}
        return {**rows, **self.world.drain_power_cycles()}


class SimTableDevice:
    """Turntable protocol over the in-process world."""

    def __init__(self, world: SimWorld) -> None:
        self.world = world

    def _now(self) -> float:
        self.world.advance()
        t = self.world.t
        self._apply_faults(t)
        return t

    def _apply_faults(self, t: float) -> None:
        """Injected table fault / open interlock: fault bits, and the drive stops (mode off)."""
        faults = self.world.faults
        faults.tick(t)
        fault, interlock = faults.active("table_fault", t), faults.active("interlock", t)
        for ax in self.world.table.axes:
            ax.fault = fault
        tripped = fault or interlock
        if tripped and not getattr(self, "_tripped", False):
            self.world.table.command(t, [OFF] * 3, np.zeros(3))
        self._tripped = tripped

    def _refuse_if_tripped(self) -> None:
        if getattr(self, "_tripped", False):
            raise DeviceFault("table: motion refused, drive faulted or interlock open")

    def move(self, angles: NDArray[np.float64]) -> None:
        self.check_value(angles, None)
        self._now()
        self._refuse_if_tripped()
        self.world.table.command(self._now(), [POSITION] * 3, np.asarray(angles, float))

    def set_rate(self, rates: NDArray[np.float64]) -> None:
        rates = np.asarray(rates, float)
        self.check_value(None, rates)
        t = self._now()
        self._refuse_if_tripped()
        for ax, r in zip(self.world.table.axes, rates):
            if not math.isnan(r):
                ax.command(t, RATE, float(r))

    def stop(self) -> None:
        self.world.table.command(self._now(), [OFF] * 3, np.zeros(3))

    def read(self) -> TableState:
        t = self._now()
        ang, rate, status = self.world.table.measured(t)
        if self.world.faults.active("interlock", t):
            status = tuple(int(s) | AxisStatus.INTERLOCK_OPEN for s in status)
        return TableState(time=t, angle=ang, rate=rate, status=status)

    def check_value(self, angles: NDArray | None, rates: NDArray | None) -> None:
        self.world.cfg.limits.check(angles, rates)


class SimImuDevice:
    """Imu protocol over the in-process world; ``identity`` names the emulated unit."""

    def __init__(self, world: SimWorld) -> None:
        self.world = world
        self.identity = dict(world.imu_identity)
        #: the unit restarted after an ``imu_power`` fault (its device time began again), as a
        #: streaming driver counts it (``counters["device_restarts"]``)
        self.device_restarts = 0
        self._unpowered = False

    @property
    def counters(self) -> dict[str, int]:
        return {"device_restarts": self.device_restarts}

    def power_cycle(self) -> None:
        """The unit loses power and has it back before the next :meth:`read` (an outage shorter
        than a poll; the ``imu_power`` fault is one of a given length): that read finds it
        restarted, as after the fault."""
        self._unpowered = True

    def read(self) -> ImuBlock:
        block = self.world.take_imu()
        t = self.world.t
        faults = self.world.faults
        faults.tick(t)
        if faults.active("imu_power", t):
            self._unpowered = True
            raise LinkLost("imu", "no data (IMU without power, injected)")
        if self._unpowered:             # powered again: a new device timeline, a new turn-on bias
            self._unpowered = False
            self.device_restarts += 1
            self.world.power_cycle_imu()
        if faults.active("imu_link", t):
            raise LinkLost("imu", "no data (link down, injected)")  # samples meanwhile are lost
        return block




class SimChamberDevice:
    """Chamber protocol (rigctl.config.chamber) over the in-process world's chamber."""

    def __init__(self, world: SimWorld, safe_c: float = 25.0) -> None:
        self.world = world
        self.safe_c = safe_c
        self.identity = {"device_id": "EMU-chamber", "protocol": "in-process emulator"}

    def _now(self) -> float:
        self.world.advance()
        t = self.world.t
        faults = self.world.faults
        if faults.windows:
            faults.tick(t)
            on = faults.active("chamber_fault", t)
            if on != (self.world.chamber.fault is not None):
                self.world.chamber.inject_fault(t, "high-limit trip (injected)" if on else None)
        return t

    def set_setpoint(self, value_c: float, ramp_c_per_min: float | None = None) -> None:
        from rigctl.devices import DeviceFault
        try:
            self.world.chamber.set_setpoint(self._now(), value_c, ramp_c_per_min)
        except ValueError as exc:
            raise DeviceFault(f"chamber: {exc}") from None

    def read(self) -> Any:
        from rigctl.config.chamber import ChamberState
        t = self._now()
        s = self.world.chamber.state(t)
        return ChamberState(time=t, air_c=s["air_c"], product_c=s["product_c"], setpoint_c=s["setpoint_c"],
                            status=s["status"], fault=s["fault"])

    def stop(self) -> None:
        self.world.chamber.stop(self._now(), self.safe_c)
