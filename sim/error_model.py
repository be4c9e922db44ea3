"""The emulated IMU's error model: true specific force and rate at the IMU -> measured outputs.

API for the in-process IMU (sim/imu.py)::

    model = ImuErrorModel.from_profile(profile, rate_hz=None, seed=0)   # rate_hz overrides profile
    #   profile: a sim.profiles.ImuProfile (or a mapping read as one); the model reads its fields
    grid = model.sample_grid(n_out)          # the IMU's own clock (drift_ppm, wander, drops), n_out samples
    #   grid.t_internal (n_out*L,) true times of the internal-rate samples, run timescale, s
    #                   (output sample k near k / rate_hz x (1 + 1e-6 ppm); sample 0 at t = 0)
    #   grid.t_eval     (n_out*L,) = t_internal - time_delay_s: evaluate the table's kinematics HERE
    #   grid.t_out (n_out,), grid.counter (n_out,) uint64, grid.keep (n_out,) bool (False = dropped)
    f_meas, w_meas, temp = model.apply(grid.t_internal, f_true, w_true, temperature=None, w_dot=None)
    #   f_true (n_out*L, 3) m/s^2 specific force at the table's rotation centre in body axes,
    #   w_true (n_out*L, 3) rad/s body rate (table + Earth), both at grid.t_eval;
    #   w_dot optional (n_out*L, 3) rad/s^2 (else backward differences of w_true, carried);
    #   temperature optional (n_out*L,) degC to replace the warm-up model (e.g. a chamber);
    #   returns (n_out, 3) m/s^2, (n_out, 3) rad/s, (n_out,) degC at the output rate
    # Blocks may have any n_out; results are bit-identical however a run is split into blocks.
    # With no frontend.internal_rate_hz (L = 1) and the clock effect off, apply(t, f, w) is a
    # drop-in for DeclaredImuModel.apply on the nominal grid t = k / rate_hz.
    model.truth()   # JSON-serialisable dict of every true parameter, SI, units in key names

Per internal sample (L = internal_rate / output_rate)::

    f = f_true + w x (w x r) + dw/dt x r + f_vib(t)          (lever arm, vibration)
    w = w_true + w_vib(t)
    F = b_a + b_on_a + c_ba dT + (M_a + diag(c_sa dT)) f + k2_a f^2 + 0.5 u |f|
    W = b_g + b_on_g + c_bg dT + (M_g + diag(c_sg dT)) w + k2 w^2 + k3 w^3 + G f + A_ae f^2
    dT = T(t) - T_ref,  T(t) = T0 + dT_w (1 - exp(-(t + t_on)/tau)),  T_ref = T0 + dT_w unless set
    (t: run time; t_on = power_on_time_s, the time since power-on when the run starts)

then each sensor: Butterworth low-pass at the internal rate, decimation, noise at the output rate
(:class:`rigctl.sim.noise.NoiseGenerator`, Q on the integrated output), ADC LSB and saturation.
The noise coefficients are those of the output (as Allan analyses of output data give them), so
noise is added after the low-pass: the output's Allan deviation is exactly
``theoretical_avar(coefficients, tau, rate_hz, extra_white_var=LSB^2/12)``.
Table non-orthogonality and levelling / north errors belong to the table's kinematics: use
:func:`rigctl.sim.effects.table_body_references` (same convention as rigctl.frames.body_references)
with ``**model.table_geometry()``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from . import effects as fx
from . import fused as _fused
from .frontend import FrontEnd
from rigctl.solvers.noise_coefficients import to_json

from .noise import NoiseGenerator
from .profiles import ClockEffect, GSensitivity, ImuProfile, TableGeometry, Warmup, given


def _vec(x: Any, default: float = 0.0) -> np.ndarray:
    return np.broadcast_to(np.asarray(default if x is None else x, dtype=float), (3,)).copy()


def _mat(x: Any) -> np.ndarray:
    return np.zeros((3, 3)) if x is None else np.asarray(x, dtype=float).reshape(3, 3)


def _or(x: Any, default: Any) -> Any:
    """A profile value, or ``default`` when the profile does not give it."""
    return default if x is None else x


def _on(effect: Any) -> Any:
    """The effect's settings when it is enabled, else None."""
    return effect if effect.enabled else None


@dataclass
class SampleGrid:
    """Times of the next block of IMU samples (see module docstring)."""

    t_internal: np.ndarray
    t_eval: np.ndarray
    t_out: np.ndarray
    counter: np.ndarray
    keep: np.ndarray


class ImuErrorModel:
    """Measured IMU outputs from true kinematics; see the module docstring for the equations."""

    def __init__(self, profile: ImuProfile, rate_hz: float | None = None, seed: int = 0):
        self.profile = profile
        self.seed = int(seed)
        self.output_rate_hz = float(rate_hz or _or(profile.rate_hz, 100.0))
        fe = profile.frontend
        internal = float(fe.internal_rate_hz or self.output_rate_hz)
        if internal < self.output_rate_hz:
            internal = self.output_rate_hz
        internal = self.output_rate_hz * max(1, round(internal / self.output_rate_hz))
        ss = np.random.SeedSequence(self.seed)
        s_gn, s_an, s_clk, s_on, s_vib, s_temp, s_pre = ss.spawn(7)
        order = int(_or(fe.filter_order, 2))
        self.gyro_fe = FrontEnd(self.output_rate_hz, internal, fe.gyro_bandwidth_hz, order,
                                fe.gyro_lsb_rad_per_s, fe.gyro_full_scale_rad_per_s)
        self.accel_fe = FrontEnd(self.output_rate_hz, internal, fe.accel_bandwidth_hz, order,
                                 fe.accel_lsb_m_per_s2, fe.accel_full_scale_m_per_s2)
        self.internal_rate_hz = internal
        self.decimation = self.gyro_fe.decimation
        g, a = profile.gyro, profile.accel
        #: the noise coefficients of each sensor's three axes (the generators' input)
        self.gyro_coefficients = g.noise.coefficients()
        self.accel_coefficients = a.noise.coefficients()
        self.gyro_noise = NoiseGenerator(self.gyro_coefficients, self.output_rate_hz, s_gn, g.noise.flicker_density())
        self.accel_noise = NoiseGenerator(self.accel_coefficients, self.output_rate_hz, s_an,
                                          a.noise.flicker_density())
        # declared errors
        self.gyro_bias = _vec(g.bias_rad_per_s)
        self.gyro_M = np.diag(1.0 + _vec(g.scale_error)) + _mat(g.misalignment_rad) * (1 - np.eye(3))
        self.accel_bias = _vec(a.bias_m_per_s2)
        self.accel_M = np.diag(1.0 + _vec(a.scale_error)) + _mat(a.misalignment_rad) * (1 - np.eye(3))
        self.accel_k2 = _vec(a.quadratic_per_m_per_s2)
        # switchable effects: each one's settings (sim.profiles), None when off
        eff = profile.effects
        self.warmup = _on(eff.warmup)
        self.turn_on = _on(eff.turn_on_bias)
        self.gsens = _on(eff.g_sensitivity)
        self.asym = _on(eff.accel_scale_asymmetry)
        self.nonlin = _on(eff.gyro_nonlinearity)
        self.lever = _on(eff.lever_arm)
        self.delay = _on(eff.time_delay)
        self.vib = _on(eff.vibration)
        self.clock_cfg = _on(eff.clock)
        self.geometry = _on(eff.table_geometry)
        #: time since power-on when the run starts, s: the warm-up (and the noise's K walk and
        #: R ramp, which start at power-on) are that far along at run time 0; the sample grid
        #: itself starts at run time 0 (counter 0 at t = 0)
        self.power_on_time_s = float(_or(profile.power_on_time_s, 0.0))
        if self.power_on_time_s < 0:
            raise ValueError("power_on_time_s must be >= 0 (time since power-on at run start)")
        self.T_ref = None
        if self.warmup:
            wu = self.warmup
            self.T_ref = float(_or(wu.T_ref_degC, wu.T0_degC + wu.dT_degC))
        # K random walk and R ramp accumulated between power-on and the run start (a constant
        # from the run's point of view): N(0, K^2 t_on) + R t_on per axis
        rng_pre = np.random.default_rng(s_pre)
        self.gyro_power_on_offset = self._noise_offset(self.gyro_noise.params, rng_pre)
        self.accel_power_on_offset = self._noise_offset(self.accel_noise.params, rng_pre)
        self.time_delay_s = float(self.delay.delay_s) if self.delay else 0.0
        self.turn_on_gyro = np.zeros(3)
        self.turn_on_accel = np.zeros(3)
        #: the turn-on biases' own stream: the first at construction, one more per power cycle
        self._turn_on_rng = np.random.default_rng(s_on)
        self.power_cycles = 0
        self._draw_turn_on()
        if self.vib:
            k = len(_or(self.vib.freqs_hz, []))
            self.vib_phase = np.random.default_rng(s_vib).uniform(0, 2 * np.pi, (k, 3))
        c = self.clock_cfg or ClockEffect()
        self.clock = fx.ClockModel(
            self.output_rate_hz, _or(c.drift_ppm, 0.0), _or(c.wander_ppm, 0.0), _or(c.wander_tau_s, 600.0),
            _or(c.drop_probability, 0.0), _or(c.drop_max_burst, 1), 0.0, s_clk)
        self._temp_rng = np.random.default_rng(s_temp)
        self._dw = fx.AngularAcceleration()
        self._t_last_out = -1.0 / self.output_rate_hz

    def _draw_turn_on(self) -> None:
        """A new turn-on bias (b_on ~ N(0, sigma^2) per axis, :func:`rigctl.sim.effects.turn_on_bias`)
        when the ``turn_on_bias`` effect is on; else it stays zero."""
        if self.turn_on:
            self.turn_on_gyro, self.turn_on_accel = fx.turn_on_bias(
                self._turn_on_rng, float(_or(self.turn_on.gyro_sigma_rad_per_s, 0.0)),
                float(_or(self.turn_on.accel_sigma_m_per_s2, 0.0)))
            self._fp = None     # the compiled path's constant biases are built again

    def power_cycle(self) -> tuple[np.ndarray, np.ndarray]:
        """The unit lost power and is back: a new turn-on bias, drawn from the unit's seeded
        stream (the ``turn_on_bias`` effect's sigmas; none when it is off), replaces the last one.
        Returns the new turn-on biases (gyro (3,) rad/s, accel (3,) m/s^2). The warm-up, noise and
        clock go on as before (only the bias is modelled as restarting)."""
        self.power_cycles += 1
        self._draw_turn_on()
        return self.turn_on_gyro.copy(), self.turn_on_accel.copy()

    def _noise_offset(self, params: Mapping[str, Any], rng: np.random.Generator) -> np.ndarray:
        """Value of the K random walk plus the R ramp at run start, power_on_time_s after power-on."""
        t_on = self.power_on_time_s
        n = rng.standard_normal(3)  # drawn whatever t_on is, so the draw never shifts
        K = _vec(params.get("K", 0.0))
        R = _vec(params.get("R", 0.0))
        return K * np.sqrt(t_on) * n + R * t_on

    @classmethod
    def from_profile(cls, profile: ImuProfile | Mapping[str, Any], rate_hz: float | None = None,
                     seed: int = 0) -> "ImuErrorModel":
        """The model of a profile (an :class:`ImuProfile`, or a mapping read as one)."""
        return cls(ImuProfile.read(profile), rate_hz, seed)

    # ------------------------------------------------------------------------------------------
    def sample_grid(self, n_out: int) -> SampleGrid:
        """True times of the next n_out output samples (IMU clock) and their internal-rate grid."""
        t_out, keep, _ = self.clock.next(n_out)
        L = self.decimation
        counter = np.arange(self.clock.counter - n_out, self.clock.counter, dtype=np.uint64)
        prev = np.concatenate([[self._t_last_out], t_out[:-1]])
        self._t_last_out = float(t_out[-1])
        frac = (np.arange(1, L + 1) / L)[None, :]
        t_int = (prev[:, None] + (t_out - prev)[:, None] * frac).ravel()
        return SampleGrid(t_int, t_int - self.time_delay_s, t_out, counter, keep)

    def temperature(self, t: np.ndarray) -> np.ndarray:
        """True sensor temperature (degC) at times t (run timescale, s)."""
        w = self.warmup
        if not w:
            return np.full(len(t), 25.0)
        return fx.warmup_temperature(np.asarray(t) + self.power_on_time_s, w.T0_degC, w.dT_degC, w.tau_s)

    def apply(self, t: np.ndarray, f_true: np.ndarray, w_true: np.ndarray, temperature: np.ndarray | None = None,
              w_dot: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Measured (f (n,3) m/s^2, w (n,3) rad/s, T (n,) degC) at the output rate from internal-rate truth."""
        t = np.asarray(t, dtype=float)
        if _fused.HAVE_NUMBA and len(t) and len(t) % self.decimation == 0:
            T = self.temperature(t) if temperature is None else np.broadcast_to(
                np.asarray(temperature, float), t.shape)
            F_out, W_out = self._internal_fused(t, f_true, w_true, T, w_dot)
            return self._output(F_out, W_out, T)
        f = np.array(f_true, dtype=float)
        w = np.array(w_true, dtype=float)
        if self.lever:
            dw = self._dw(t, w) if w_dot is None else np.asarray(w_dot, dtype=float)
            f += fx.lever_arm_specific_force(w, dw, _vec(self.lever.r_m))
        if self.vib:
            fr = self.vib.freqs_hz
            zero = np.zeros((len(fr), 3))
            fv, wv = fx.vibration_many(t, fr, [_or(self.vib.accel_amp_m_per_s2, zero),
                                               _or(self.vib.gyro_amp_rad_per_s, zero)], self.vib_phase)
            f += fv
            w += wv
        T = self.temperature(t) if temperature is None else np.broadcast_to(np.asarray(temperature, float), t.shape)
        F = fx.accel_declared(f, self.accel_bias + self.turn_on_accel + self.accel_power_on_offset,
                              self.accel_M, self.accel_k2)
        W = fx.gyro_declared(w, self.gyro_bias + self.turn_on_gyro + self.gyro_power_on_offset, self.gyro_M)
        if self.warmup:
            wu = self.warmup
            dT = T - self.T_ref
            F += fx.thermal_error(f, dT, _vec(wu.accel_bias_tc_m_per_s2_per_K), _vec(wu.accel_scale_tc_per_K))
            W += fx.thermal_error(w, dT, _vec(wu.gyro_bias_tc_rad_per_s_per_K), _vec(wu.gyro_scale_tc_per_K))
        if self.asym:
            F += fx.scale_asymmetry_error(f, _vec(self.asym.asymmetry))
        if self.nonlin:
            W += fx.gyro_nonlinearity_error(w, _vec(self.nonlin.k2_per_rad_per_s), _vec(self.nonlin.k3_per_rad2_per_s2))
        if self.gsens:
            ae = self.gsens.anisoelastic_rad_per_s_per_m2_per_s4
            W += fx.g_sensitivity_error(f, _mat(self.gsens.G_rad_per_s_per_m_per_s2), None if ae is None else _mat(ae))
        F_out = self.accel_fe.filter_decimate(F)
        W_out = self.gyro_fe.filter_decimate(W)
        return self._output(F_out, W_out, T)

    def _output(self, F_out: np.ndarray, W_out: np.ndarray, T: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Output-rate part of :meth:`apply`: noise, ADC, temperature channel."""
        n = F_out.shape[0]
        F_out = self.accel_fe.digitize(self.accel_noise.next(n, F_out))
        W_out = self.gyro_fe.digitize(self.gyro_noise.next(n, W_out))
        T_out = T[self.decimation - 1 :: self.decimation].copy()
        if self.warmup:
            T_out += self._temp_rng.standard_normal(n) * float(_or(self.warmup.temp_noise_degC, 0.0))
            lsb = float(_or(self.warmup.temp_lsb_degC, 0.0))
            if lsb > 0:
                T_out = np.round(T_out / lsb) * lsb
        return F_out, W_out, T_out

    def _fused_params(self) -> tuple:
        """Constant arguments of sim.fused._internal (built once)."""
        if getattr(self, "_fp", None) is None:
            z3, z33 = np.zeros(3), np.zeros((3, 3))
            wu, gs = self.warmup or Warmup(), self.gsens or GSensitivity()
            ae = gs.anisoelastic_rad_per_s_per_m2_per_s4
            if self.vib:
                fr = np.asarray(self.vib.freqs_hz, dtype=float)
                zero = np.zeros((len(fr), 3))
                fa = np.asarray(_or(self.vib.accel_amp_m_per_s2, zero), dtype=float).reshape(-1, 3)
                ga = np.asarray(_or(self.vib.gyro_amp_rad_per_s, zero), dtype=float).reshape(-1, 3)
                ph = np.asarray(self.vib_phase, dtype=float)
                vib = (fr, fa * np.cos(ph), fa * np.sin(ph), ga * np.cos(ph), ga * np.sin(ph),
                       fa != 0.0, ga != 0.0)
            else:
                vib = (np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)),
                       np.zeros((0, 3)), np.zeros((0, 3), bool), np.zeros((0, 3), bool))
            self._fp = (
                _vec(self.lever.r_m) if self.lever else z3, *vib,
                self.accel_bias + self.turn_on_accel + self.accel_power_on_offset,
                np.ascontiguousarray(self.accel_M, dtype=float), np.asarray(self.accel_k2, float),
                self.gyro_bias + self.turn_on_gyro + self.gyro_power_on_offset,
                np.ascontiguousarray(self.gyro_M, dtype=float),
                float(self.T_ref) if self.warmup else 0.0,
                _vec(wu.accel_bias_tc_m_per_s2_per_K), _vec(wu.accel_scale_tc_per_K),
                _vec(wu.gyro_bias_tc_rad_per_s_per_K), _vec(wu.gyro_scale_tc_per_K),
                0.5 * _vec(self.asym.asymmetry) if self.asym else z3,
                _vec(self.nonlin.k2_per_rad_per_s) if self.nonlin else z3,
                _vec(self.nonlin.k3_per_rad2_per_s2) if self.nonlin else z3,
                _mat(gs.G_rad_per_s_per_m_per_s2) if self.gsens else z33,
                _mat(ae) if (self.gsens and ae is not None) else z33)
        return self._fp

    def _internal_fused(self, t: np.ndarray, f_true: np.ndarray, w_true: np.ndarray, T: np.ndarray,
                        w_dot: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Everything of :meth:`apply` at the internal rate, low-pass and decimation included, in
        one compiled pass (sim.fused); the same arithmetic as the numpy path, state carried."""
        f_true = np.ascontiguousarray(f_true, dtype=float)
        w_true = np.ascontiguousarray(w_true, dtype=float)
        T = np.ascontiguousarray(T, dtype=float)
        n, L = len(t), self.decimation
        dw_in = w_dot is not None
        dw = np.ascontiguousarray(w_dot, dtype=float) if dw_in else np.zeros((1, 3))
        p = self._fused_params()
        gs_a = bool(self.gsens and self.gsens.anisoelastic_rad_per_s_per_m2_per_s4 is not None)
        d = self._dw
        prev = (np.array([d._t, *d._w[0]]) if d._t is not None else
                np.array([t[0] - 1.0, *w_true[0]]))
        fes = (self.accel_fe, self.gyro_fe)
        eff = [bool(self.lever), dw_in, bool(self.vib), bool(self.warmup), bool(self.asym),
               bool(self.nonlin), bool(self.gsens), gs_a]
        if any(fe._sos is not None and fe._zi is None for fe in fes):
            # the filter starts in steady state for the first filtered sample (as filter_decimate)
            f1, w1 = np.empty((1, 3)), np.empty((1, 3))
            dummy = (np.zeros((1, 6)), np.zeros((1, 3, 2)))
            _fused._internal(t[:1], f_true[:1], w_true[:1], T[:1], dw[:1], np.array(eff + [False, False]),
                             prev.copy(), *p, *dummy, *dummy, 1, f1, w1)
            for fe, x0 in zip(fes, (f1[0], w1[0])):
                if fe._sos is not None and fe._zi is None:
                    fe._zi = fe.steady_state(x0)
        filt = [(fe._sos, fe._zi) if fe._sos is not None else (np.zeros((1, 6)), np.zeros((1, 3, 2)))
                for fe in fes]
        flags = np.array(eff + [fes[0]._sos is not None, fes[1]._sos is not None])
        out_f, out_w = np.empty((n // L, 3)), np.empty((n // L, 3))
        _fused._internal(t, f_true, w_true, T, dw, flags, prev, *p, *filt[0], *filt[1], L, out_f, out_w)
        if self.lever and not dw_in:
            d._t, d._w = float(prev[0]), prev[1:].reshape(1, 3).copy()
        return out_f, out_w

    # ------------------------------------------------------------------------------------------
    def table_geometry(self) -> dict:
        """Keyword arguments for effects.table_attitude_and_rate (zeros when the effect is off);
        worked out once per geometry (a frozen TableGeometry; the emulator asks at every block)."""
        cached = self.__dict__.get("_geometry_kw")
        if cached is None or cached[0] is not self.geometry:
            g = self.geometry or TableGeometry()
            kw = {"nonorth_rad": list(_vec(g.nonorth_rad)), "level_x_rad": float(_or(g.level_x_rad, 0.0)),
                  "level_y_rad": float(_or(g.level_y_rad, 0.0)), "north_rad": float(_or(g.north_rad, 0.0))}
            cached = self._geometry_kw = (self.geometry, kw)
        return {k: (list(v) if isinstance(v, list) else v) for k, v in cached[1].items()}

    def truth(self) -> dict:
        """Every true parameter, JSON-serialisable, SI, units in the key names."""
        def js(x: Any) -> Any:
            if isinstance(x, np.ndarray):
                return x.tolist()
            if isinstance(x, dict):
                return {k: js(v) for k, v in x.items()}
            if isinstance(x, (list, tuple)):
                return [js(v) for v in x]
            if isinstance(x, (np.floating, np.integer)):
                return x.item()
            return x
        out = {
            "profile_name": self.profile.name, "seed": self.seed,
            "output_rate_hz": self.output_rate_hz, "power_on_time_s": self.power_on_time_s,
            # three axes each, rigctl.solvers.noise_coefficients.to_json (SI; units in "units")
            "gyro_noise": [to_json(m) for m in self.gyro_coefficients],
            "accel_noise": [to_json(m) for m in self.accel_coefficients],
            "gyro_bias_rad_per_s": self.gyro_bias, "gyro_turn_on_bias_rad_per_s": self.turn_on_gyro,
            "gyro_scale_misalignment_matrix": self.gyro_M,
            "accel_bias_m_per_s2": self.accel_bias, "accel_turn_on_bias_m_per_s2": self.turn_on_accel,
            "accel_scale_misalignment_matrix": self.accel_M, "accel_quadratic_per_m_per_s2": self.accel_k2,
            "gyro_noise_offset_at_run_start_rad_per_s": self.gyro_power_on_offset,
            "accel_noise_offset_at_run_start_m_per_s2": self.accel_power_on_offset,
            "time_delay_s": self.time_delay_s,
            "noise_model": ("IEEE 952 terms per axis (rigctl.sim.noise): Q on the integrated output, "
                            "B as a 1/f pole-zero cascade (flicker_pairs_per_decade, default 2), added at "
                            "the output rate after the front-end low-pass; exact curve: "
                            "rigctl.sim.noise.theoretical_avar(coefficients, tau, rate_hz, LSB^2/12)"),
            "effects": {name: (given(cfg) if cfg else {"enabled": False}) for name, cfg in [
                ("warmup", self.warmup), ("turn_on_bias", self.turn_on), ("g_sensitivity", self.gsens),
                ("accel_scale_asymmetry", self.asym), ("gyro_nonlinearity", self.nonlin), ("lever_arm", self.lever),
                ("time_delay", self.delay), ("vibration", self.vib), ("clock", self.clock_cfg),
                ("table_geometry", self.geometry)]},
        }
        if self.vib:
            out["effects"]["vibration"]["phase_rad"] = self.vib_phase
        if self.warmup:
            out["effects"]["warmup"]["T_ref_degC"] = self.T_ref  # what apply() uses
        out.update(self.gyro_fe.truth("gyro", "rad_per_s"))
        out.update(self.accel_fe.truth("accel", "m_per_s2"))
        return js(out)
