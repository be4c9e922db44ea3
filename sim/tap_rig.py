"""Taps in the in-process rig: an emulated operator with a tap hammer, and the pulse input.

When the engine runs a ``taps`` step it calls ``rig.operator.prompt(step, t_start, duration)``;
:class:`SimTapOperator` then schedules ``step.expected_taps`` taps spread over the window
``[t_start + margin, t_start + duration - margin]`` (one tap per equal slot, see
:meth:`SimTapOperator.prompt`). The physics is that of :mod:`rigctl.sim.taps` (same :class:`~rigctl.sim.taps.TapParams`):

* tap ``i`` at true time ``t_i`` with amplitude ``a_i = sign * exp(ln(median) + sigma * N(0,1))``
  (m/s^2) and direction ``u_i`` (configured axis + ``cross_axis_fraction * N(0,1)`` on each axis)
  adds ``a_i u_i g(t - t_i)`` to the TRUE specific force at the IMU, where ``g`` is the mount's
  response (``"none"``: :data:`rigctl.sim.taps.RINGING` on the physics grid; ``"second_order"``:
  :func:`rigctl.sim.taps.unit_peak_second_order`). The IMU model then applies its own front end
  (low-pass, decimation, clock), so the tap is seen through the sensor's response;
* the hammer's electrical edges (latency, jitter, bounce, missed pulses, spurious edges and the
  receiver's timeguard) come from :func:`rigctl.sim.taps._receiver`, on the run (reference)
  timescale; :class:`SimPulses` delivers each edge once the clock has passed it.

Every blow and edge drawn is also kept as truth rows (:data:`TRUTH_TABLES`, drained by the
recorder into /truth/taps and /truth/edges through :meth:`SimTapOperator.drain_truth_rows`).

Times in s (run timescale), accelerations in m/s^2.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rigctl.devices import Clock, Pulses
from rigctl.settings import number, yaml_keys

from . import taps as T

AXES = T.AXES

#: Truth drawn during the run, written by the recorder as /truth/<table>/<column>
#: (column: (per-row shape, dtype, units)); docs/data-format.md.
TRUTH_TABLES: dict[str, dict[str, tuple[tuple[int, ...], Any, str]]] = {
    "taps": {  # one row per blow: hammer taps and spurious IMU spikes, in the order drawn
        "time_s": ((), np.float64, "s"),            # true time of the blow, run timescale
        "amplitude_m_s2": ((), np.float64, "m/s^2"),  # signed peak a_i
        "direction": ((3,), np.float64, "1"),       # u_i, body axes (1 on the tap axis)
        "hammer": ((), np.uint8, "1"),              # 1 = hammer tap, 0 = spurious spike (no edge)
        "missed": ((), np.uint8, "1"),              # 1 = the hammer made no edge for this tap
        "edge_time_s": ((), np.float64, "s"),       # its main edge (NaN if none), run timescale
        "edge_logged": ((), np.uint8, "1"),         # 1 = the receiver logged that edge
        "bounces": ((), np.int32, "1"),             # bounce edges after the main edge
        "step": ((), np.int32, "1"),                # procedure step index that prompted it
    },
    "edges": {  # every electrical edge, logged or not
        "time_s": ((), np.float64, "s"),
        "kind": ((), "S16", ""),                    # tap | bounce | spurious
        "tap_row": ((), np.int64, "1"),             # row of /truth/taps, -1 for a spurious edge
        "logged": ((), np.uint8, "1"),              # 1 = in /pulses (outside the timeguard)
    },
}


@dataclass(frozen=True, kw_only=True)
class TapRigSettings(T.TapParams):
    """``pulses.sim``: the hammer, response and receiver (:class:`rigctl.sim.taps.TapParams`)
    and how the emulated operator schedules the taps of a ``taps`` step."""

    margin_s: float = number(1.0, minimum=0)
    slot_jitter: float = number(0.3, minimum=0, maximum=0.45)
    seed: int = number(0, minimum=0, integer=True)

    def tap_params(self) -> T.TapParams:
        return T.TapParams(**{f.name: getattr(self, f.name) for f in fields(T.TapParams)})


#: Options of ``pulses.sim`` besides the TapParams fields.
EXTRA_KEYS = tuple(k for k in yaml_keys(TapRigSettings) if k not in yaml_keys(T.TapParams))


class TapField:
    """Scheduled taps and the specific force they add on any time grid (carried across blocks)."""

    def __init__(self, params: T.TapParams) -> None:
        self.p = params
        self.time = np.empty(0)
        self.amplitude = np.empty(0)
        self.direction = np.empty((0, 3))
        self.is_hammer = np.empty(0, dtype=bool)
        self._seen = np.empty(0, dtype=int)  # grid samples already past each tap ("none")

    def add(self, t: NDArray, amp: NDArray, direction: NDArray, hammer: NDArray) -> None:
        self.time = np.concatenate([self.time, t])
        self.amplitude = np.concatenate([self.amplitude, amp])
        self.direction = np.concatenate([self.direction, direction])
        self.is_hammer = np.concatenate([self.is_hammer, hammer])
        self._seen = np.concatenate([self._seen, np.zeros(t.size, dtype=int)])

    def apply(self, t: NDArray, f: NDArray) -> None:
        """Add every tap's force to ``f`` ((n, 3), m/s^2) at the true times ``t`` (n,), in place.

        Successive calls must cover successive, increasing stretches of one grid."""
        if not self.time.size or not t.size:
            return
        p = self.p
        length = p.response_length_s if p.response == "second_order" else math.inf
        live = np.flatnonzero((self.time <= t[-1]) & (self.time + length >= t[0]))
        for i in live:
            ti, ai, ui = self.time[i], self.amplitude[i], self.direction[i]
            k0 = int(np.searchsorted(t, ti, side="left"))
            if p.response == "second_order":
                k1 = int(np.searchsorted(t, ti + p.response_length_s))
                g = T.unit_peak_second_order(t[k0:k1] - ti, p.natural_freq_hz, p.damping)
                f[k0:k1] += ai * g[:, None] * ui[None, :]
            else:  # the RINGING pattern from the first grid sample at or after the tap
                s = int(self._seen[i])
                if s >= T.RINGING.size:
                    continue
                k = np.arange(k0, min(k0 + T.RINGING.size - s, t.size))
                f[k] += ai * T.RINGING[s: s + k.size, None] * ui[None, :]
                self._seen[i] = s + k.size


class SimTapOperator:
    """The emulated operator: taps the IMU when a taps step prompts, and fires the hammer edges."""

    def __init__(self, params: T.TapParams, margin_s: float = 1.0, slot_jitter: float = 0.3,
                 seed: int = 0) -> None:
        self.p, self.margin_s, self.slot_jitter = params, margin_s, slot_jitter
        self.field = TapField(params)
        self.rng = np.random.default_rng(np.random.SeedSequence([seed, 0x7A9]))
        self.pulse_time = np.empty(0)  # every edge the receiver logged, run time s
        self.pulse_kind = np.empty(0, dtype="U8")
        self.sessions: list[dict[str, Any]] = []
        self.n_truth_rows = 0  # rows of the taps truth table so far
        self._truth: dict[str, list[dict[str, np.ndarray]]] = {name: [] for name in TRUTH_TABLES}

    def prompt(self, step: Any, t_start: float, duration: float) -> None:
        """Tap ``step.expected_taps`` times in ``[t_start, t_start + duration]``: the usable
        window (less ``margin_s`` at both ends) is cut into equal slots, one tap per slot at the
        slot centre + U(-slot_jitter, slot_jitter) slot widths."""
        n = int(getattr(step, "expected_taps", None) or 0)
        if n <= 0:
            return
        p, rng = self.p, self.rng
        t0, usable = t_start + self.margin_s, duration - 2 * self.margin_s
        if usable <= 0:
            t0, usable = t_start, duration
        slot = usable / n
        tap_t = t0 + (np.arange(n) + 0.5 + rng.uniform(-self.slot_jitter, self.slot_jitter, n)) * slot
        spikes: list[float] = []
        tries = 0
        while len(spikes) < p.spurious_spikes and tries < 1000:  # away from taps, as sim/taps.py
            tries += 1
            ts = float(rng.uniform(t0, t0 + usable))
            if np.all(np.abs(tap_t - ts) > min(2.0, slot / 2)) and all(abs(s - ts) > 2.0 for s in spikes):
                spikes.append(ts)
        all_t = np.concatenate([tap_t, np.asarray(spikes, float)])
        hammer = np.concatenate([np.ones(n, bool), np.zeros(len(spikes), bool)])
        amp = p.sign * np.exp(math.log(p.amplitude_median_m_s2)
                              + p.amplitude_log_sigma * rng.standard_normal(all_t.size))
        amp[~hammer] *= p.spurious_spike_scale
        direction = p.cross_axis_fraction * rng.standard_normal((all_t.size, 3))
        direction[:, p.axis] = 1.0
        self.field.add(all_t, amp, direction, hammer)
        # hammer edges on the window's own timescale (spurious edges fall inside the window)
        et, ek, ei, logged = T.hammer_edges(rng, p, all_t - t_start, hammer, duration)
        et = et + t_start
        if self.pulse_time.size:  # the receiver's dead time carries over from earlier sessions
            logged = logged & (et - self.pulse_time[-1] >= p.timeguard_s)
        pt, pk = et[logged], ek[logged].astype(str)
        self.pulse_time = np.concatenate([self.pulse_time, pt])
        self.pulse_kind = np.concatenate([self.pulse_kind, pk.astype("U8")])
        step_index = int(getattr(step, "index", -1))
        self._record_truth(step_index, all_t, amp, direction, hammer, et, ek, ei, logged)
        main = ek == "tap"
        self.sessions.append({"step": step_index, "t_start_s": t_start,
                              "duration_s": duration, "n_taps": n, "n_spurious_spikes": len(spikes),
                              "n_pulses": int(pt.size),
                              "n_pulses_missed": n - int((main & logged).sum())})

    def _record_truth(self, step: int, tap_t: NDArray, amp: NDArray, direction: NDArray,
                      hammer: NDArray, et: NDArray, ek: NDArray, ei: NDArray, logged: NDArray) -> None:
        """Rows of the truth tables (TRUTH_TABLES) for one prompt's taps and edges."""
        n = tap_t.size
        main = ek == "tap"
        edge_t = np.full(n, np.nan)
        edge_logged = np.zeros(n, np.uint8)
        edge_t[ei[main]] = et[main]
        edge_logged[ei[main]] = logged[main]
        bounces = np.bincount(ei[ek == "bounce"], minlength=n).astype(np.int32)
        row0 = self.n_truth_rows
        self._truth["taps"].append({
            "time_s": tap_t.astype(float), "amplitude_m_s2": amp.astype(float),
            "direction": direction.astype(float), "hammer": hammer.astype(np.uint8),
            "missed": (hammer & np.isnan(edge_t)).astype(np.uint8), "edge_time_s": edge_t,
            "edge_logged": edge_logged, "bounces": bounces, "step": np.full(n, step, np.int32)})
        self._truth["edges"].append({
            "time_s": et.astype(float), "kind": np.asarray([str(k) for k in ek], dtype="S16"),
            "tap_row": np.where(ei >= 0, ei + row0, -1).astype(np.int64),
            "logged": logged.astype(np.uint8)})
        self.n_truth_rows += n

    def drain_truth_rows(self) -> dict[str, dict[str, NDArray]]:
        """Truth rows drawn since the last call, {table: {column: array}} (TRUTH_TABLES)."""
        out = {}
        for name, parts in self._truth.items():
            if parts:
                out[name] = {c: np.concatenate([p[c] for p in parts]) for c in TRUTH_TABLES[name]}
                parts.clear()
        return out

    def truth(self) -> dict[str, Any]:
        """Tap and receiver parameters (SI), JSON-serialisable. The taps themselves are drawn
        during the run: :meth:`drain_truth_rows` (the recorder's /truth/taps and /truth/edges)."""
        return {"taps": asdict(self.p), "margin_s": self.margin_s, "slot_jitter": self.slot_jitter}


class SimPulses:
    """Pulse input of the emulated GNSS receiver: edges with time <= now, each delivered once."""

    def __init__(self, operator: SimTapOperator, clock: Clock) -> None:
        self.operator, self.clock = operator, clock
        self._next = 0

    def read(self) -> Pulses:
        t = self.operator.pulse_time
        k = int(np.searchsorted(t, self.clock.now(), side="right"))
        out, self._next = t[self._next:k], max(self._next, k)
        return Pulses(out.copy(), source="sim")
