"""Tap-hammer emulation: taps seen by an IMU, hammer edges logged by a reference receiver.

Pure, seeded numpy code (no I/O). Model (all SI, times in seconds of the reference clock):

IMU clock (sample counter ``c`` -> reference time)::

    t_ref(c) = offset_s + c * T * (1 + drift_ppm * 1e-6) + A_w * sin(2 pi c T / P_w + phi_w)

with ``T = 1 / rate_hz`` the nominal sample interval. A positive ``drift_ppm`` means the IMU
clock runs slow (each count lasts longer than nominal), so fewer samples than nominal are
recorded over a reference interval.

Tap ``i`` at true time ``t_i`` adds to the specific force of every sample ``k``::

    f_k += a_i * u_i * g(t_ref(c_k) - t_i)

where ``u_i`` is mostly the configured axis (unit weight) plus small cross-axis terms, ``a_i``
the tap peak amplitude (m/s^2) and ``g`` the unit-peak sensor response:

* ``"none"``: the tap appears at the first sample with ``t_ref(c_k) >= t_i`` (as the paper's
  MTi-G), followed by a short fixed ringing ``RINGING``; no sub-sample information.
* ``"second_order"``: the impulse response of ``H(s) = wn^2 / (s^2 + 2 zeta wn s + wn^2)``,
  ``h(t) = wn / sqrt(1 - zeta^2) exp(-zeta wn t) sin(wd t)`` for ``t >= 0``, scaled to unit
  peak, evaluated at the continuous sample instants (so sub-sample timing is present).

The hammer's electrical edge is at ``t_i + latency + N(0, jitter^2)``; contact bounce adds
edges a few ms later; a pulse is missed with a set count or probability; spurious edges
without taps and spurious IMU spikes without edges can be added. The receiver logs an edge
only if it comes at least ``timeguard_s`` after the last logged one (NovAtel MARKCONTROL).
Dropped-sample runs remove samples (the counter keeps counting, unless
``counter_gaps_visible`` is False, in which case the counter is a contiguous host index).
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from rigctl import schema as S
from rigctl.settings import Settings, internal, number, numbers, setting, text
from rigctl.solvers.tap_detect import SecondOrderResponse
from rigctl.yamlio import LocDict

#: Shape of a tap for the "none" response, in unit-peak amplitude per sample after the tap.
RINGING = np.array([1.0, -0.45, 0.2, -0.08])


@dataclass
class ClockParams:
    """IMU clock relative to the reference clock (see module docstring)."""

    offset_s: float = 0.0
    drift_ppm: float = 0.0
    wander_amplitude_s: float = 0.0
    wander_period_s: float = 3600.0
    wander_phase_rad: float = 0.0

    def time_of_counter(self, counter: np.ndarray | float, rate_hz: float) -> np.ndarray:
        """Reference time (s) of IMU sample counter value(s) ``counter`` (may be fractional)."""
        c = np.asarray(counter, dtype=float)
        period = 1.0 / rate_hz
        t = self.offset_s + c * period * (1.0 + self.drift_ppm * 1e-6)
        if self.wander_amplitude_s:
            t = t + self.wander_amplitude_s * np.sin(
                2 * np.pi * c * period / self.wander_period_s + self.wander_phase_rad)
        return t

    def counter_of_time(self, t: np.ndarray | float, rate_hz: float) -> np.ndarray:
        """Fractional counter at reference time ``t`` (inverse of :meth:`time_of_counter`)."""
        t = np.asarray(t, dtype=float)
        scale = (1.0 + self.drift_ppm * 1e-6) / rate_hz
        c = (t - self.offset_s) / scale
        for _ in range(3):  # Newton iterations for the (slow, small) wander term
            c = c - (self.time_of_counter(c, rate_hz) - t) / scale
        return c


AXES = {"x": 0, "y": 1, "z": 2}


def _axis(d: LocDict, key: str, default: int = 2) -> int:
    return AXES[S.get_str(d, key, choices=tuple(AXES))]


def _sign(d: LocDict, key: str, default: float = 1.0) -> float:
    v = float(S.get_number(d, key))
    if v not in (-1.0, 1.0):
        raise S.error(d, key, f"'sign' must be -1 or +1, got {d[key]!r}",
                      "it is the direction of the blow along 'axis'; the size of the "
                      "blow is 'amplitude_median_m_s2'")
    return v


def _count(default: int) -> Any:
    return number(default, minimum=0, maximum=10000, integer=True)


@dataclass(frozen=True, kw_only=True)
class TapParams(Settings):
    """Hammer, sensor-response and receiver parameters (SI units); as settings: the keys of a
    rig config's ``pulses.sim`` (:class:`rigctl.sim.tap_rig.TapRigSettings`, docs/emulator.md)."""

    axis: int = setting(2, read=_axis)  # config: x | y | z
    amplitude_median_m_s2: float = number(40.0, minimum=0)
    amplitude_log_sigma: float = number(0.4, minimum=0)
    sign: float = setting(1.0, read=_sign)
    cross_axis_fraction: float = number(0.05, minimum=0)
    response: str = text("none", choices=("none", "second_order"))
    natural_freq_hz: float = number(30.0, minimum=0)
    damping: float = number(0.7, minimum=0)
    response_length_s: float = number(0.25, minimum=0)
    range_m_s2: float | None = internal(None)  # saturation level; None = no clipping
    latency_s: float = number(0.0)
    jitter_s: float = number(0.0, minimum=0)
    bounce_probability: float = number(0.0, minimum=0, maximum=1)
    bounce_max_count: int = _count(3)
    bounce_spacing_s: tuple[float, float] = numbers((0.5e-3, 4e-3), length=2)
    missed_count: int = _count(0)  # exact number of taps whose pulse is missed
    missed_probability: float = number(0.0, minimum=0, maximum=1)
    spurious_pulses: int = _count(0)  # edges with no tap
    spurious_spikes: int = _count(0)  # IMU spikes with no edge
    spurious_spike_scale: float = number(0.7, minimum=0)  # spike amplitude relative to the tap median
    timeguard_s: float = number(0.4, minimum=0)

    def check(self, d: LocDict) -> None:
        if self.response == "second_order" and not 0.0 < self.damping < 1.0:
            raise S.error(d, "damping", "'damping' must be in (0, 1) for response second_order")


@dataclass
class ScheduleParams:
    """When taps happen: ``n_groups`` groups of ``taps_per_group`` taps."""

    group_starts_s: tuple[float, ...] = (30.0,)
    taps_per_group: int = 10
    interval_s: tuple[float, float] = (1.0, 3.0)  # uniform spacing between taps in a group


@dataclass
class TapTruth:
    """Everything true about one emulated tap session."""

    rate_hz: float
    clock: ClockParams
    taps: TapParams
    tap_time: np.ndarray  # (n,) reference s, hammer taps then spurious spikes
    tap_amplitude: np.ndarray  # (n,) m/s^2 (signed, on the tap axis)
    tap_is_hammer: np.ndarray  # (n,) bool, False = spurious spike
    tap_pulse_index: np.ndarray  # (n,) index into pulse_time, -1 if no pulse
    tap_recorded: np.ndarray  # (n,) bool, False if the tap fell in a data loss
    pulse_kind: np.ndarray  # (P,) "tap" | "bounce" | "spurious"
    pulse_tap_index: np.ndarray  # (P,) index into tap_time, -1 for spurious
    dropouts: list[tuple[int, int]] = field(default_factory=list)  # (first counter, length)
    counter_gaps_visible: bool = True
    n_samples_total: int = 0  # samples the IMU produced, recorded or not

    def time_of_counter(self, counter: np.ndarray | float) -> np.ndarray:
        """True reference time (s) of IMU counter value(s)."""
        return self.clock.time_of_counter(counter, self.rate_hz)

    def params_json(self) -> str:
        """JSON of every true parameter (for /truth attrs params_json)."""
        return json.dumps({
            "rate_hz": self.rate_hz, "clock": asdict(self.clock), "taps": asdict(self.taps),
            "dropouts": [list(map(int, d)) for d in self.dropouts],
            "counter_gaps_visible": self.counter_gaps_visible,
            "n_samples_total": self.n_samples_total,
            "n_taps_hammer": int(self.tap_is_hammer.sum()),
            "n_spurious_spikes": int((~self.tap_is_hammer).sum()),
            "n_pulses_missed": int((self.tap_is_hammer & (self.tap_pulse_index < 0)).sum()),
            "n_spurious_pulses": int((self.pulse_kind != "tap").sum()),
        })


@dataclass
class TapSession:
    """Emulator output: what the IMU recorded and what the receiver logged, plus truth."""

    rate_hz: float
    counter: np.ndarray  # (N,) uint64 recorded sample counters
    specific_force: np.ndarray  # (N, 3) m/s^2
    pulse_time: np.ndarray  # (P,) reference s
    truth: TapTruth


def unit_peak_second_order(t: np.ndarray, natural_freq_hz: float, damping: float) -> np.ndarray:
    """Impulse response of wn^2/(s^2 + 2 zeta wn s + wn^2) scaled to unit peak; 0 for t < 0.

    The same function as the sync solver's template family
    (:class:`rigctl.solvers.tap_detect.SecondOrderResponse`, one definition): the solver learns
    the frequency and damping from the taps, it is not told the emulator's. Its behaviour on
    responses outside this family (two modes, clipping, another axis) is tested with a generator
    of its own in tests/test_sync_foreign_taps.py."""
    if not 0.0 < float(damping) < 1.0:
        raise ValueError("damping must be in (0, 1)")
    return SecondOrderResponse(natural_freq_hz, float(damping))(t)


def _schedule(rng: np.random.Generator, sched: ScheduleParams) -> np.ndarray:
    times = []
    for start in sched.group_starts_s:
        gaps = rng.uniform(*sched.interval_s, size=sched.taps_per_group - 1)
        times.append(start + np.concatenate([[0.0], np.cumsum(gaps)]))
    return np.sort(np.concatenate(times))


def _receiver(rng: np.random.Generator, p: TapParams, tap_t: np.ndarray, hammer: np.ndarray,
              t_end: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Electrical edges and the receiver's timeguard; returns pulse times/kind/tap and map."""
    et, ek, ei, keep = hammer_edges(rng, p, tap_t, hammer, t_end)
    pt, pk, pi = et[keep], ek[keep].astype(str), ei[keep]
    tap_pulse = np.full(tap_t.size, -1, dtype=int)
    for j in np.flatnonzero(pk == "tap"):
        tap_pulse[pi[j]] = j
    return pt, pk, pi, tap_pulse


def hammer_edges(rng: np.random.Generator, p: TapParams, tap_t: np.ndarray, hammer: np.ndarray,
                 t_end: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every electrical edge the hammer makes, sorted by time: (time s, kind "tap" | "bounce" |
    "spurious", index of its tap or -1, whether the receiver logs it under its timeguard)."""
    n = tap_t.size
    hammer_idx = np.flatnonzero(hammer)
    fires = np.zeros(n, dtype=bool)
    fires[hammer_idx] = rng.random(hammer_idx.size) >= p.missed_probability
    if p.missed_count:
        cand = hammer_idx[fires[hammer_idx]]
        fires[rng.choice(cand, size=min(p.missed_count, cand.size), replace=False)] = False
    edges_t, edges_kind, edges_tap = [], [], []
    for i in np.flatnonzero(fires):
        te = tap_t[i] + p.latency_s + p.jitter_s * rng.standard_normal()
        edges_t.append(te), edges_kind.append("tap"), edges_tap.append(i)
        if rng.random() < p.bounce_probability:
            nb = rng.integers(1, p.bounce_max_count + 1)
            for tb in te + np.cumsum(rng.uniform(*p.bounce_spacing_s, size=nb)):
                edges_t.append(tb), edges_kind.append("bounce"), edges_tap.append(i)
    for ts in rng.uniform(0.0, t_end, size=p.spurious_pulses):
        edges_t.append(ts), edges_kind.append("spurious"), edges_tap.append(-1)
    order = np.argsort(edges_t, kind="stable")
    et = np.asarray(edges_t, dtype=float)[order]
    ek = np.asarray(edges_kind, dtype=object)[order]
    ei = np.asarray(edges_tap, dtype=int)[order]
    keep = np.zeros(et.size, dtype=bool)
    last = -np.inf
    for j, t in enumerate(et):  # receiver dead time
        if t - last >= p.timeguard_s:
            keep[j], last = True, t
    return et, ek, ei, keep


def simulate_taps(rate_hz: float, duration_s: float, schedule: ScheduleParams,
                  taps: TapParams, clock: ClockParams | None = None, *,
                  noise_std_m_s2: float = 0.01,
                  base_specific_force: np.ndarray | None = None,
                  gravity_m_s2: float = 9.81,
                  dropouts: list[tuple[float, int]] | None = None,
                  random_dropouts: int = 0, dropout_length: int = 32,
                  counter_gaps_visible: bool = True, counter_start: int = 0,
                  seed: int = 0) -> TapSession:
    """Emulate a tap session.

    ``base_specific_force`` (n_total, 3) m/s^2 is the noise floor for every sample the IMU
    produces (recorded or not); if None it is ``[0, 0, gravity] + N(0, noise_std^2)``.
    ``dropouts`` gives (reference time s, length in samples) runs of lost samples;
    ``random_dropouts`` adds that many runs of ``dropout_length`` at random times at least
    1 s from any tap.  Spurious spikes are placed at least 2 s from any hammer tap.
    """
    rng = np.random.default_rng(seed)
    clock = clock or ClockParams()
    n_total = int(np.floor(clock.counter_of_time(duration_s, rate_hz))) + 1
    c_all = np.arange(n_total, dtype=np.int64)
    t_all = clock.time_of_counter(c_all, rate_hz)

    tap_t = _schedule(rng, schedule)
    tap_t = tap_t[(tap_t > t_all[0] + 1.0) & (tap_t < t_all[-1] - 1.0)]
    spikes = []
    while len(spikes) < taps.spurious_spikes:
        ts = rng.uniform(t_all[0] + 1.0, t_all[-1] - 1.0)
        if np.all(np.abs(tap_t - ts) > 2.0) and all(abs(s - ts) > 2.0 for s in spikes):
            spikes.append(ts)
    all_t = np.concatenate([tap_t, np.asarray(spikes, dtype=float)])
    hammer = np.concatenate([np.ones(tap_t.size, bool), np.zeros(len(spikes), bool)])
    amp = taps.sign * np.exp(np.log(taps.amplitude_median_m_s2)
                             + taps.amplitude_log_sigma * rng.standard_normal(all_t.size))
    amp[~hammer] *= taps.spurious_spike_scale
    direction = taps.cross_axis_fraction * rng.standard_normal((all_t.size, 3))
    direction[:, taps.axis] = 1.0

    if base_specific_force is None:
        f = noise_std_m_s2 * rng.standard_normal((n_total, 3))
        f[:, 2] += gravity_m_s2
    else:
        f = np.array(base_specific_force, dtype=float, copy=True)
        if f.shape != (n_total, 3):
            raise ValueError(f"base_specific_force must have shape ({n_total}, 3)")
    for ti, ai, ui in zip(all_t, amp, direction):
        k0 = int(np.searchsorted(t_all, ti, side="left"))
        if taps.response == "none":
            k = np.arange(k0, min(k0 + RINGING.size, n_total))
            f[k] += ai * RINGING[: k.size, None] * ui[None, :]
        elif taps.response == "second_order":
            k1 = int(np.searchsorted(t_all, ti + taps.response_length_s))
            g = unit_peak_second_order(t_all[k0:k1] - ti, taps.natural_freq_hz, taps.damping)
            f[k0:k1] += ai * g[:, None] * ui[None, :]
        else:
            raise ValueError(f"unknown response {taps.response!r}")
    if taps.range_m_s2 is not None:
        np.clip(f, -taps.range_m_s2, taps.range_m_s2, out=f)

    pulse_t, pulse_kind, pulse_tap, tap_pulse = _receiver(rng, taps, all_t, hammer, duration_s)

    runs = [(int(np.floor(clock.counter_of_time(t, rate_hz))), int(n)) for t, n in dropouts or []]
    tries = 0
    while len(runs) < len(dropouts or []) + random_dropouts and tries < 10000:
        tries += 1
        c0 = int(rng.integers(n_total // 20, n_total - dropout_length - 1))
        if np.all(np.abs(all_t - t_all[c0]) > 1.0 + dropout_length / rate_hz):
            runs.append((c0, int(dropout_length)))
    keep = np.ones(n_total, dtype=bool)
    for c0, n in runs:
        keep[c0:c0 + n] = False
    k_tap = np.searchsorted(t_all, all_t)
    recorded = keep[np.minimum(k_tap, n_total - 1)]
    counter = c_all[keep].astype(np.uint64) + np.uint64(counter_start)
    if not counter_gaps_visible:
        counter = np.arange(counter.size, dtype=np.uint64) + np.uint64(counter_start)
    if counter_start:
        clock = ClockParams(clock.offset_s - counter_start * (1 + clock.drift_ppm * 1e-6) / rate_hz,
                            clock.drift_ppm, clock.wander_amplitude_s, clock.wander_period_s,
                            clock.wander_phase_rad
                            - 2 * np.pi * counter_start / rate_hz / clock.wander_period_s)
        runs = [(c0 + counter_start, n) for c0, n in runs]
    truth = TapTruth(rate_hz=rate_hz, clock=clock, taps=taps, tap_time=all_t,
                     tap_amplitude=amp, tap_is_hammer=hammer, tap_pulse_index=tap_pulse,
                     tap_recorded=recorded, pulse_kind=pulse_kind, pulse_tap_index=pulse_tap,
                     dropouts=sorted(runs), counter_gaps_visible=counter_gaps_visible,
                     n_samples_total=n_total)
    return TapSession(rate_hz=rate_hz, counter=counter, specific_force=f[keep],
                      pulse_time=pulse_t, truth=truth)


#: Trigger + detector jitter implied by the paper: sqrt(5.48^2 - 2.89^2) ms.
PAPER_JITTER_S = float(np.sqrt(0.005482**2 - (0.01 / np.sqrt(12.0))**2))


def experiment1(seed: int = 1, *, response: str = "none", jitter_s: float = PAPER_JITTER_S,
                counter_gaps_visible: bool = True, **tap_overrides: float) -> TapSession:
    """Scenario shaped like the paper's experiment 1: 100 Hz, ~71 min, 14 groups of 10 taps
    every ~5 min, 2 pulses missed, one 32-sample data loss, 1 ppm clock, paper-like jitter."""
    rng = np.random.default_rng(seed + 1000)
    starts = tuple(60.0 + 300.0 * np.arange(14) + rng.uniform(-20, 20, 14))
    params = TapParams(response=response, jitter_s=jitter_s, missed_count=2,
                       **tap_overrides)  # type: ignore[arg-type]
    return simulate_taps(100.0, 4300.0, ScheduleParams(starts, 10, (1.0, 3.0)), params,
                         ClockParams(offset_s=0.137, drift_ppm=1.0), noise_std_m_s2=0.02,
                         random_dropouts=1, dropout_length=32,
                         counter_gaps_visible=counter_gaps_visible, seed=seed)


def experiment2(seed: int = 2, *, response: str = "none", jitter_s: float = PAPER_JITTER_S,
                drift_ppm: float = 85.0, **tap_overrides: float) -> TapSession:
    """Scenario shaped like the paper's experiment 2: 3 h 20 min at 100 Hz, internal clock
    ``drift_ppm`` (85), 10 taps at the start and 10 at the end."""
    duration = 3 * 3600.0 + 20 * 60.0
    params = TapParams(response=response, jitter_s=jitter_s, **tap_overrides)  # type: ignore[arg-type]
    return simulate_taps(100.0, duration, ScheduleParams((30.0, duration - 60.0), 10, (1.0, 3.0)),
                         params, ClockParams(offset_s=0.0886, drift_ppm=drift_ppm),
                         noise_std_m_s2=0.02, seed=seed)
