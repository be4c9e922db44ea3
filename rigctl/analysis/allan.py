"""The Allan pipeline: a recording's IMU channels in, deviations, intervals and the IEEE 952 fit
out (the application layer; ``rigctl allan``, the ``solve: [allan]`` hook, the report and the
batch runner call it, and only present its results).

Streams /imu/angular_rate (rad/s) and /imu/specific_force (m/s^2) in chunks (bounded memory,
all selected axes in one pass), computes the overlapping Allan deviation (fast mode by default,
``exact`` for the fully overlapping sums), Stable32-style noise identification, EDF and 68 % /
95 % intervals, the joint IEEE 952 fit with its self-check (:mod:`rigctl.solvers.allan_fit`),
and stores everything under /results/allan of the recording (attrs schema_version,
created_utc, json; curves as datasets with ``units``).
"""
from __future__ import annotations

import contextlib
import gc
import json
import math
import os
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import InputError
from ..progress import WorkProgress
from ..jsonable import jsonable
from ..recording.recorder import write_results
from ..sensor_axes import ACCEL_AXES, GYRO_AXES
from ..recording.recording_reader import (PLAUSIBLE, RowPieces, RowReader, as_array, check_finite,
                                          open_recording, release, sample_rate)
from ..solvers import allan as A
from ..solvers import allan_edf as E
from ..solvers import allan_fit as F
from ..solvers import allan_checks as CHK
from ..solvers import allan_kernels as KER
from ..solvers import allan_noise_id as NID
from ..solvers.allan_stream import blas_single_thread
from ..solvers import allan_tones as TN
from ..solvers import noise_coefficients as NC
from ..solvers.noise_coefficients import NoiseCoefficients, as_coefficients, from_json, in_field_units
from . import allan_drift as AD
from . import allan_quiet as QS
from . import allan_excursions as EXA
from . import production

#: axis (rigctl.sensor_axes: the one spelling) -> (dataset, column, sensor); gyros first, the
#: order of the output
AXES = {**{g: ("/imu/angular_rate", i, "gyro") for i, g in enumerate(GYRO_AXES)},
        **{a: ("/imu/specific_force", i, "accel") for i, a in enumerate(ACCEL_AXES)}}
#: display unit of the deviation per sensor: (label, factor from SI)
DEV_UNITS = {"gyro": ("deg/h", 180.0 / math.pi * 3600.0), "accel": ("mg", 1000.0 / F.G0)}
MIN_SAMPLES = 64
CHUNK_ROWS = 1 << 19  # rows per read: 2 chunks of 6 axes in flight = 48 MB
HEAD_POINTS = 1 << 22  # full-resolution phase kept for noise ID at short taus
DEC_POINTS = 1 << 21  # the phase is also kept decimated to at most ~this many points
#: /results/allan layout: 2 added each axis' fit["coefficients"] (rigctl.solvers.noise_coefficients
#: .to_json) and dropped fit["coeff_sq_si"]; a version-1 group is read by nothing: re-run rigctl allan
SCHEMA_VERSION = 2
#: worker threads for the per-axis work (both cores of a 2-core machine)
WORKERS = max(1, min(2, os.cpu_count() or 1))
#: after the first chunk, a dataset's three columns go through one compiled pass (running-sum
#: phase of each axis written into its accumulator, the spike prefilter's block extremes, the
#: finiteness check) instead of a column copy, a check and a screen pass per axis; False: the
#: per-axis path for every chunk (the same results, bit for bit; tests compare the two)
FUSED = True
#: the noise IDs read from the full-resolution head are taken while the rest of the record
#: streams (False: all of them in the analysis after the last chunk; the same values)
EARLY_NOISE_ID = True
#: each dataset's chunks follow each other as soon as its own tasks are done (a chain per
#: dataset, :func:`_pipelined`) instead of every dataset waiting for the slowest at the end of
#: each chunk (False: the loop with that barrier; the same numbers)
PIPELINED = True
#: with them (same task), the tone detection's periodogram of the head (TONE_POINTS samples
#: of it: complete, unchanged, once the head is): off the tail after the last chunk (False:
#: in the analysis; the same values)
EARLY_TONES = True
#: with :data:`PIPELINED`, the first axis' dataset leads: its chunk tasks go before the other
#: dataset's on the workers, so it finishes first, and its axes' analyses (noise ID, EDF,
#: fits: Python holding the GIL) run while the other dataset's last chunks are summed
#: (compiled, without the GIL) instead of all six after the last chunk (False: both datasets
#: side by side, every analysis after the last chunk; the same numbers)
LEAD_DATASET = True
#: ... by at most this many chunks (2^19 rows each): enough for its analyses to run beside the
#: other dataset's last chunks (~0.3 s of Python against ~5 ms per chunk), not so many that
#: the other dataset's chunks run alone for long (one dataset's chain keeps ~1.3 cores busy:
#: its one pass, then its three sums on two workers)
LEAD_CHUNKS = 32
#: the axes that finish together (a dataset's, after its last chunk) get their noise IDs on
#: the decimated copy as tasks of their own, queued before their analyses
#: (:meth:`_AxisStream.dec_noise_ids`: compiled lag-1 sums without the GIL, beside the other
#: axes' fits; False: inside each analysis; the same values)
SPLIT_NOISE_IDS = True
#: the interpreter's GIL switch interval (s) while a record streams and its axes are analysed
#: (restored afterwards; None: left alone). A worker coming back from a compiled kernel (the
#: sums, the one pass; they run without the GIL) needs the GIL for its few lines of Python
#: before the next kernel, and while another thread runs Python (a dataset's fits, the
#: database import) it gets it only when that thread is made to drop it: after the switch
#: interval, 5 ms by default, against ~1.5 ms per kernel call. ~8 such waits per chunk
#: would stall the other dataset's chunks during the lead dataset's fits
SWITCH_INTERVAL_S: float | None = 5e-4


#: a wait for a result or a thread in the analysis gives the main thread back to Python this often, s
WAIT_SLICE_S = 0.1


def _result(fut: Any) -> Any:
    """``fut.result()``, waited for in slices of :data:`WAIT_SLICE_S`. A wait without a timeout
    was not woken by SIGINT / SIGTERM: the handler (which stops the analysis, rigctl.run.runner)
    ran only once the result came -- a SIGINT to ``rigctl serve`` 1 s into allan on a 2-minute
    capture ended the job 23-27 s later, 3 times in 3 at load 16-19, the main thread waiting in
    Future.result for an axis' Gauss-Markov fits. Between slices the handler runs."""
    while True:
        try:
            return fut.result(timeout=WAIT_SLICE_S)
        except TimeoutError:
            continue


def _join(thread: threading.Thread) -> None:
    """``thread.join()`` in slices of :data:`WAIT_SLICE_S` (as :func:`_result`)."""
    while thread.is_alive():
        thread.join(WAIT_SLICE_S)


class _PriorityPool:
    """A fixed set of worker threads taking tasks by rank, then in the order queued (a
    :class:`concurrent.futures.ThreadPoolExecutor` takes them in the order queued only):
    ``submit_at(rank, fn, *args)``, lower ranks first; ``submit`` and ``map`` at rank 0.
    Returns :class:`concurrent.futures.Future` objects; leaving the ``with`` block waits
    for every queued task."""

    def __init__(self, workers: int):
        import heapq
        from concurrent.futures import Future

        self._heapq, self._future = heapq, Future
        self._heap: list = []
        self._seq = 0
        self._cond = threading.Condition()
        self._closed = False
        self._threads = [threading.Thread(target=self._work, name=f"allan-worker-{i}",
                                          daemon=True) for i in range(max(1, workers))]
        for t in self._threads:
            t.start()

    def submit_at(self, rank: int, fn: Callable, *args: Any) -> Any:
        fut = self._future()
        with self._cond:
            if self._closed:
                raise RuntimeError("pool shut down")
            self._heapq.heappush(self._heap, (rank, self._seq, fut, fn, args))
            self._seq += 1
            self._cond.notify()
        return fut

    def submit(self, fn: Callable, *args: Any) -> Any:
        return self.submit_at(0, fn, *args)

    def map(self, fn: Callable, items: Any) -> Any:
        futs = [self.submit(fn, x) for x in items]
        return (_result(f) for f in futs)

    def _work(self) -> None:
        # every task with OpenBLAS at one thread in this worker (thread-local): the analysis'
        # matrices are small, and a call's rounding must not depend on whether OpenBLAS ran it
        # on one thread or two (the step test's 150 x 150 factorisations differed in the last
        # digits from run to run of the same record)
        with blas_single_thread():
            self._work_loop()

    def _work_loop(self) -> None:
        while True:
            with self._cond:
                while not self._heap and not self._closed:
                    self._cond.wait()
                if not self._heap:
                    return
                _, _, fut, fn, args = self._heapq.heappop(self._heap)
            if not fut.set_running_or_notify_cancel():
                continue
            try:
                res = fn(*args)
            except BaseException as e:  # noqa: BLE001 - handed to the future's owner
                fut.set_exception(e)
            else:
                fut.set_result(res)
            del fut, fn, args

    def shutdown(self, abandon: bool = False) -> None:
        """Take no more tasks and wait until the workers have run every queued one; ``abandon``:
        cancel the tasks not started yet and wait for none (the workers end once the tasks in
        flight end, in the background; their results are dropped)."""
        with self._cond:
            self._closed = True
            if abandon:
                for _, _, fut, _, _ in self._heap:
                    fut.cancel()
                self._heap.clear()
            self._cond.notify_all()
        if not abandon:
            for t in self._threads:
                _join(t)

    def __enter__(self) -> "_PriorityPool":
        return self

    def __exit__(self, exc_type: Any, *exc: Any) -> None:
        # leaving on an exception -- an interrupted analysis (SIGINT / SIGTERM), a failed task --
        # abandons the rest: nobody reads those results, and waiting for them held the
        # interruption back by the rest of the analysis (a pure computation writing nothing:
        # one axis' Gauss-Markov fits alone took ~10 s at load 12; SIGTERM 2 s into allan on a
        # 2-minute capture ended the process 12.6 s later)
        self.shutdown(abandon=exc_type is not None)


class _AxisStream:
    """Accumulates one axis: Allan sums (streamed), plus for the noise identification a
    full-resolution phase head and the whole phase decimated by ``dec`` (bounded memory)."""

    def __init__(self, tau0: float, ms: np.ndarray, mode: str, n_rate: int):
        self.acc = A.OadevAccumulator(tau0, ms, mode)
        self.ms = np.asarray(self.acc.ms)
        # gap skipping (Stable32): the sums of the finished gap-free stretches, their term
        # counts and the fully overlapping terms they stand for
        self.stretches = 0
        self._sums = np.zeros(self.ms.size)
        self._counts = np.zeros(self.ms.size, dtype=np.int64)
        self._terms = np.zeros(self.ms.size, dtype=np.int64)
        self.x_base = 0.0  # phase at the end of the previous stretch (noise-ID copies)
        self.x_last = 0.0  # phase of the last point given to the noise-ID copies
        self.dec = 1
        while (n_rate + 1) // self.dec > DEC_POINTS:
            self.dec *= 2
        # both phase copies are filled in place (their sizes are known): no list of pieces
        # and no concatenation, which would hold them twice at the peak
        self._head = np.empty(min(HEAD_POINTS, n_rate) + 1)
        self.n_head = 0
        self.n_total = n_rate  # the samples the record will give (the noise IDs' N)
        self.head_released = False  # (head_noise_ids took all it is read for: dropped)
        self._nid: dict[tuple[int, int], int] = {}  # noise IDs taken early (head_noise_ids)
        self._tones: dict[str, Any] | None = None  # tone detection taken early (head_noise_ids)
        self._dec = np.empty(n_rate // self.dec + 1)
        self._dec[0] = 0.0  # x[0] = 0
        self.n_dec = 1
        self.part = np.empty(0)  # rate samples of the unfinished decimation block
        self.tau0 = tau0
        self.x_dec = 0.0  # phase at the last decimated point
        self.x_head = 0.0
        self.n_rate = 0
        self.quant_step: float | None = None  # output step, from the first block
        self.spike_sigma: float | None = None  # robust sd of the residual, from the first block
        self.spike_basis = ""  # what that sd was read from (CHK.spike_scale)
        self.spikes: list[np.ndarray] = []  # indices (within the analysed range)
        self.spike_size: list[np.ndarray] = []  # |residual| / sd of each

    def screen(self, y: np.ndarray, first: int, exclude: bool,
               before: np.ndarray | None = None, after: np.ndarray | None = None) -> np.ndarray:
        """Quantization step (first block) and spikes (every block) of these samples, ``first``
        their index in the analysed range; with ``exclude`` the spikes are replaced by the
        running median of their neighbours (the returned samples). ``before`` / ``after``:
        the record's samples just before and after the block (CHK.window_medians), so that
        the windows of its first and last samples are those of one pass over the record."""
        if self.n_rate == 0 and not self.spikes:
            self.quant_step = CHK.quantization_step(y)
        if self.spike_sigma is None:  # the first block sets sigma (running median of all)
            idx, med, sd, self.spike_basis = CHK.find_spikes_scaled(
                y, None, step=self.quant_step, before=before, after=after)
            med = med[idx]
            self.spike_sigma = sd
        else:  # the same spikes, the median only where one can be (CHK.spikes_beyond)
            sd = self.spike_sigma
            idx, med = CHK.spikes_beyond(y, sd, before=before, after=after)
        if idx.size:
            self.spikes.append(idx + first)
            self.spike_size.append(np.abs(y[idx] - med) / max(sd, 1e-300))
            if exclude:
                y = y.copy()
                y[idx] = med
        return y

    def takes_phase(self) -> bool:
        """Whether the next chunk can come as phase points written by the caller
        (:meth:`phase_target`, :meth:`screen_block`, :meth:`add_written`): the first chunk
        (which sets the offset, the quantization step and the spike sigma) is done."""
        return self.spike_sigma is not None and self.acc.can_take_phase()

    def phase_target(self, n: int) -> np.ndarray:
        return self.acc.rate_target(n)

    def screen_block(self, y: np.ndarray, first: int, exclude: bool,
                     extremes: tuple[np.ndarray, np.ndarray],
                     before: np.ndarray | None = None, after: np.ndarray | None = None
                     ) -> np.ndarray | None:
        """As :meth:`screen` for a later chunk, starting from the block extremes the running-
        sum pass took (``y`` may be a column view of the read block). Returns the samples with
        the spikes replaced when ``exclude`` finds any (they must then be added with
        :meth:`add`), else None (the phase written into :meth:`phase_target` stands)."""
        idx, med = CHK.spikes_beyond(y, self.spike_sigma, extremes=extremes, before=before,
                                     after=after)
        if not idx.size:
            return None
        sd = self.spike_sigma
        self.spikes.append(idx + first)
        self.spike_size.append(np.abs(y[idx] - med) / max(sd, 1e-300))
        if not exclude:
            return None
        y = np.array(y, dtype=np.float64)
        y[idx] = med
        return y

    def add_written(self, n: int) -> None:
        """Add the ``n`` samples whose phase points were written into :meth:`phase_target`.
        Without a gap so far the accumulator's phase index is the record's, so the decimated
        copy for the noise ID is taken inside its cascade, while the points are in cache (a
        strided pass over the chunk afterwards costs a cache miss per point: 0.6 s of the
        12 h x 6-axis file's CPU)."""
        g0 = self.n_rate + 1
        acc = self.acc
        if self.stretches == 0 and not self.x_base and acc.cascade is not None \
                and acc.n_phase == g0:
            n_dec = self.n_dec
            got = acc.commit_rate(n, self._dec[n_dec:], self.dec)
            x = acc.chunk_phase
            if got:
                self.n_dec += got
                self.x_dec = float(self._dec[self.n_dec - 1])
            self._add_head(x)
            self.x_last = float(x[-1])
            self.n_rate += n
            return
        acc.commit_rate(n)
        x = acc.chunk_phase
        self._add_phase(x + self.x_base if self.x_base else x, g0)
        self.n_rate += n

    def _put_dec(self, xs: np.ndarray) -> None:
        self._dec[self.n_dec: self.n_dec + xs.size] = xs
        self.n_dec += xs.size
        self.x_dec = float(xs[-1])

    def add(self, y: np.ndarray) -> None:
        if y.size == 0:
            return
        acc = self.acc
        g0 = self.n_rate + 1  # phase index of this chunk's first point (in the whole record)
        acc.add_rate(y)
        x = acc.chunk_phase
        if x is not None and x.size == y.size:  # the accumulator's own phase: no second pass
            # after a gap (break_stretch) the accumulator's phase restarts at 0: the noise-ID
            # copies continue from the last point before the gap
            self._add_phase(x + self.x_base if self.x_base else x, g0)
            self.n_rate += y.size
            return
        c = acc.offset
        if self.n_head < HEAD_POINTS:  # full-resolution phase of the first samples
            part = y[: HEAD_POINTS - self.n_head] - c
            x = np.cumsum(part) * self.tau0 + self.x_head
            if self.n_head == 0:
                self._head[0] = 0.0
                self.n_head = 1
            self._head[self.n_head: self.n_head + x.size] = x
            self.n_head += x.size
            self.x_head = float(x[-1])
        if self.dec == 1:
            self._put_dec(np.cumsum(y - c) * self.tau0 + self.x_dec)
        else:  # block sums of dec samples, then a short running sum
            z = np.concatenate((self.part, y)) if self.part.size else y
            nb = z.size // self.dec
            if nb:
                sums = z[: nb * self.dec].reshape(nb, self.dec).sum(axis=1) - self.dec * c
                self._put_dec(np.cumsum(sums) * self.tau0 + self.x_dec)
            self.part = z[nb * self.dec:].copy()
        self.n_rate += y.size

    def break_stretch(self) -> None:
        """A gap: the terms summed so far are kept, and the next samples start a new stretch,
        so that no Allan term spans the gap (Stable32's gap skipping). The noise-ID phase
        copies run on across the gap (they only classify the noise type)."""
        acc = self.acc
        if acc.n_phase > 1:
            sums, counts, strides = acc.raw_sums()
            self._sums += sums
            self._counts += counts
            self._terms += np.maximum(0, acc.n_phase - 2 * self.ms)
            self._strides = strides
            self.stretches += 1
        self.x_base = self.x_last
        self.acc = A.OadevAccumulator(self.tau0, self.ms, acc.mode, offset=acc.offset)

    def result(self) -> A.DevResult:
        """The deviations: of the one stretch, or the sums of every gap-free stretch (terms
        touching a gap skipped, their count reduced accordingly)."""
        if self.stretches == 0:
            return self.acc.result()
        self.break_stretch()
        return A.dev_from_sums(self.ms, self.tau0, self._sums, self._counts, self._strides,
                               np.where(self._strides == 1, self._counts, self._terms),
                               self.n_rate + 1)

    def _add_head(self, x: np.ndarray) -> None:
        if self.n_head < HEAD_POINTS:  # as add(): the same points
            k = min(HEAD_POINTS - self.n_head, x.size)
            if self.n_head == 0:
                self._head[0] = 0.0
                self.n_head = 1
            self._head[self.n_head: self.n_head + k] = x[:k]
            self.n_head += k
            self.x_head = float(x[k - 1])

    def _add_phase(self, x: np.ndarray, g0: int) -> None:
        """Head and decimated copies from the phase points x[g0 + i] = x[i] (the same running
        sum as :meth:`add` builds: bit-identical head; the decimated points are the phase at
        every dec-th index instead of a running sum of block sums)."""
        self._add_head(x)
        start = (-g0) % self.dec
        if start < x.size:
            xs = x[start:: self.dec]
            self._put_dec(xs[: self._dec.size - self.n_dec])
        self.x_last = float(x[-1])

    def noise_id(self, m: int, n: int) -> int:
        """Stable32's noise ID at factor m (no hold); ``n``: the full record's term count.
        Taken early (:meth:`head_noise_ids`, :meth:`dec_noise_ids`) where it could be."""
        hit = self._nid.get((int(m), int(n)))
        if hit is not None:
            return hit
        if m % self.dec == 0:
            return NID.noise_id(self._dec[: self.n_dec], m // self.dec, "oadev", n)
        if self.head_released:  # head_noise_ids released it only with every one of these taken
            raise RuntimeError(f"noise ID at m={m}, N={n} not taken before the head was released")
        return NID.noise_id(self._head[: self.n_head], m, "oadev", n)

    def dec_noise_ids(self) -> None:
        """The noise IDs that read the decimated copy (factors a multiple of ``dec``), once
        the axis' last chunk is summed (the copy is complete), for the record's phase points
        as :meth:`result` counts them: a task of their own, queued before the analyses of
        the axes that finish together (:data:`SPLIT_NOISE_IDS`), so that the lag-1 sums
        (compiled, without the GIL; ~17 ms per axis of a 12 h x 2 kHz record) of the
        analysis the workers take last run beside the others' fits instead of inside it.
        The same calls with the same arguments as :meth:`noise_id` makes, which then finds
        them."""
        n_phase = self.n_rate + 1
        for m in self.ms.tolist():
            if m % self.dec:
                continue
            n = NID.n_terms("oadev", n_phase, m)
            try:
                self._nid[(m, n)] = NID.noise_id(self._dec[: self.n_dec], m // self.dec,
                                                 "oadev", n)
            except (ValueError, ArithmeticError):
                pass  # left to the analysis, which reports it as before

    def head_full(self) -> bool:
        """The full-resolution head is complete (it does not change any more)."""
        return self.head_released or self.n_head >= min(HEAD_POINTS, self._head.size)

    def head_noise_ids(self, n_phase: int) -> None:
        """The noise IDs that read the head (factors not a multiple of ``dec``), for a record
        of ``n_phase`` phase points, taken as soon as the head is complete (on a worker while
        the rest of the record streams: the lag-1 sums of the longest series run compiled,
        without the GIL, instead of in the analysis after the last chunk). The same calls
        with the same arguments as :meth:`noise_id` makes later, which then finds them."""
        for m in self.ms.tolist():
            if m % self.dec == 0:
                continue
            n = NID.n_terms("oadev", n_phase, m)
            try:
                self._nid[(m, n)] = NID.noise_id(self._head[: self.n_head], m, "oadev", n)
            except (ValueError, ArithmeticError):
                pass  # left to the analysis, which reports it as before
        if not EARLY_TONES:
            return
        y = _tone_rate(self)  # (a copy: the head can go before the periodogram runs)
        self._release_head(n_phase)
        self._tones = _detect_tones(self, y)

    def _release_head(self, n_phase: int) -> None:
        """Drop the full-resolution head (33.5 MB per axis at HEAD_POINTS) once nothing will
        read it again, instead of holding it to the axis' analysis: the rest of the record
        streams without the six heads (they were ~200 MB of a 12 h x 6-axis run's peak,
        docs/allan.md), and the periodogram of the tones (:meth:`head_noise_ids`, from its
        own copy of the rate) runs without it. Only when the noise IDs were taken for the
        phase points the analysis will have (``n_phase``: every sample of the range summed;
        not with windows left out) and each of them found (an error leaves the head to the
        analysis, which reports it)."""
        if n_phase != self.n_total + 1 or not self.head_full():
            return
        for m in self.ms.tolist():
            if m % self.dec and (m, NID.n_terms("oadev", n_phase, m)) not in self._nid:
                return
        self._head = np.empty(0)
        self.head_released = True

    def tone_detection(self) -> dict[str, Any]:
        """The periodogram's tone detection (:func:`_detect_tones`): taken early with the
        head's noise IDs (the head no longer changes), else now."""
        out, self._tones = self._tones, None
        return out if out is not None else _detect_tones(self)


def _screening(stream: _AxisStream, sensor: str, fit: dict, dev0: float, tau0: float,
               excluded: bool) -> dict[str, Any]:
    """Spikes and quantization of one axis (SI, and the field unit of the deviation)."""
    unit, fac = DEV_UNITS[sensor]
    idx = np.concatenate(stream.spikes) if stream.spikes else np.zeros(0, dtype=np.int64)
    size = np.concatenate(stream.spike_size) if stream.spike_size else np.zeros(0)
    spikes = {"count": int(idx.size), "fraction": idx.size / max(stream.n_rate, 1),
              "threshold_sd": CHK.SPIKE_SIGMA, "window_samples": CHK.SPIKE_WINDOW,
              "sd_si": stream.spike_sigma, "sd_from": stream.spike_basis, "excluded": bool(excluded and idx.size),
              "largest_sd": float(size.max()) if size.size else 0.0,
              "first_times_s": [float(i * tau0) for i in idx[:10]]}
    quant = None
    if stream.quant_step is not None:
        n_c = fit["coefficients"].N
        n_si = n_c.value if n_c.resolved else None
        quant = CHK.quantization_noise(stream.quant_step, tau0, n_si, dev0)
        quant[f"step_{unit}"] = stream.quant_step * fac
        quant["step_si"] = quant.pop("step")
        quant["white_N_si"] = quant.pop("white_N")
        # the file's decimal digits (a power of ten of its unit) or the sensor's output step
        quant["step_source"] = CHK.step_source(stream.quant_step, sensor)
    return {"spikes": spikes, "quantization": quant}


def fm_after_fm(ms: np.ndarray, alphas: np.ndarray) -> np.ndarray:
    """The noise types the EDF uses: past the first tau identified as an FM type (alpha <= 0),
    a phase-modulation type (alpha 1, 2) is read as white FM (alpha 0). For a rate sensor PM
    noise (white or flicker angle noise, quantization) only rules the shortest taus; at long
    taus a PM identification comes from a handful of averages whose curve happens to fall,
    and its EDF (hundreds, where a dozen averages give ~10) would make those taus look
    well determined (seen on a 12 h emulated tactical capture: alpha 1 from 4000 s on, EDF
    130-383 at 11 averages, a 95 % band narrow enough to hold B below the floor the curve
    shows and the fit left with no term at all)."""
    out = np.array(alphas, dtype=np.int64)
    order = np.argsort(np.asarray(ms), kind="stable")
    seen_fm = False
    for i in order:
        if seen_fm and out[i] > 0:
            out[i] = 0
        seen_fm = seen_fm or out[i] <= 0
    return out


def edf_skipping_gaps(alpha: int, m: int, stretch_samples: np.ndarray, stride: int = 1) -> float:
    """EDF of the overlapping Allan variance at factor m when the terms touching a gap are
    skipped: the estimate is the mean of the terms of the gap-free stretches that hold any
    (L + 1 phase points, n = L + 1 - 2m terms each), i.e. a sum of independent per-stretch
    estimates weighted by their term counts, whose EDF is Satterthwaite's
    (sum n_i)^2 / sum(n_i^2 / nu_i), nu_i Greenhall's EDF of stretch i. Taking the whole
    record's EDF instead overstates it wherever stretches are short: an Astro Pi record (237
    stretches, the longest 446 samples) kept 44 terms at m = 208, all in one stretch, with an
    EDF of 147 for the whole record (~1 for the stretch). ``stride``: the spacing of the
    terms summed (fast mode), each stretch's EDF then that of its strided terms."""
    lengths, count = np.unique(np.asarray(stretch_samples, dtype=np.int64), return_counts=True)
    num = den = 0.0
    for length, c in zip(lengths, count):
        n_terms = int(length) + 1 - 2 * int(m)
        if n_terms <= 0:
            continue
        try:
            nu = E.edf("oadev", int(alpha), int(m), int(length) + 1, int(stride))
        except ValueError:  # too few phase points for a Greenhall EDF
            continue
        if not nu > 0:
            continue
        num += c * n_terms
        den += c * n_terms ** 2 / nu
    return num * num / den if den > 0 else float("nan")


#: the periodogram reads at most this many samples of each axis (5.8 h at 100 Hz; 0.35 s)
TONE_POINTS = 1 << 21


def _tone_rate(stream: _AxisStream) -> np.ndarray:
    """The rate samples the tone detection reads (SI): the first TONE_POINTS of the axis,
    from the differences of its full-resolution phase head (a new array)."""
    y = np.diff(stream._head[: min(stream.n_head, TONE_POINTS + 1)])
    y /= stream.tau0  # (in place: one 16 MB array per axis at the tones' peak, not two)
    return y


def _detect_tones(stream: _AxisStream, y: np.ndarray | None = None) -> dict[str, Any]:
    """:func:`rigctl.solvers.allan_tones.detect_tones` on the axis' rate samples ``y``
    (:func:`_tone_rate`, taken here if not given), SI."""
    if y is None:
        y = _tone_rate(stream)
    if y.size < 1:
        return {"tones": [], "skipped": "no samples"}
    out = TN.detect_tones(y, 1.0 / stream.tau0)
    out["samples_used"] = int(y.size)
    return out


def _tones(stream: _AxisStream, sensor: str) -> dict[str, Any]:
    """Tones in the axis' rate samples (:func:`_detect_tones`, taken early when the head was
    complete before the last chunk); each tone's amplitude also in the deviation's field
    unit, and the Allan term it adds."""
    out = stream.tone_detection()
    unit, fac = DEV_UNITS[sensor]
    for t in out["tones"]:
        t[f"amp_{unit}"] = t["amp_si"] * fac
        t["amp_unit"] = unit
    for bd in out.get("bands") or []:
        bd[f"rms_{unit}"] = bd["rms_si"] * fac
        bd["rms_unit"] = unit
    return out


def analyse_axis(stream: _AxisStream, sensor: str, excluded: bool = False,
                 stretch_samples: np.ndarray | None = None, axis: str = "") -> dict[str, Any]:
    """Deviation curve, confidence and fits of one streamed axis (SI + field units).
    ``stretch_samples``: the lengths of the gap-free stretches when gaps are skipped (the EDF
    is then that of the stretches' terms: :func:`edf_skipping_gaps`). InputError naming
    ``axis`` when every sample is the same value (no curve: a channel nobody filled)."""
    res = stream.result()
    if len(res.dev) and not np.any(np.asarray(res.dev) > 0):
        others = ",".join(a for a in AXES if a != axis)
        raise InputError(f"axis {axis or sensor}: every sample is the same value: no Allan curve (a channel "
                         "the sensor, its driver or the import did not fill, or a stuck one)",
                         hint=f"leave it out, e.g. --axes {others}")
    raw = [stream.noise_id(int(m), NID.n_terms("oadev", res.n_phase, int(m))) for m in res.m]
    held = NID.apply_hold(res.m, raw, res.n_phase, "oadev")
    alphas = fm_after_fm(res.m, np.array([NID.clamp_alpha(int(a), "oadev") for a in held]))
    strides = res.stride if len(res.stride) == len(res.m) else np.ones_like(res.m)
    if stretch_samples is not None and len(stretch_samples) > 1:
        edfs = np.array([edf_skipping_gaps(int(a), int(m), stretch_samples, int(k))
                         for a, m, k in zip(alphas, res.m, strides)])
    else:  # the EDF of the terms actually summed (fast mode: strided, Greenhall's S = m/s)
        edfs = np.array([E.edf("oadev", int(a), int(m), res.n_phase, int(k))
                         for a, m, k in zip(alphas, res.m, strides)])
    lo68, hi68 = E.chi2_interval(res.dev, edfs, E.ONE_SIGMA)
    lo95, hi95 = E.chi2_interval(res.dev, edfs, 0.95)
    unit, fac = DEV_UNITS[sensor]
    tones = _tones(stream, sensor)
    gapped = stretch_samples is not None and len(stretch_samples) > 1
    fit = F.fit_terms(res.tau_s, res.dev, edfs, sensor, tau0=res.tau0_s, n_phase=res.n_phase,
                      tones=[{"freq_hz": t["freq_hz"], "amp_si": t["amp_si"]}
                             for t in tones["tones"]],
                      stretch_samples=stretch_samples if gapped else None)
    pw = F.piecewise_readoffs(res.tau_s, res.dev, sensor)
    si = "rad/s" if sensor == "gyro" else "m/s^2"
    dev0 = float(res.dev[0]) if len(res.m) and int(res.m[0]) == 1 else float("nan")
    ybar, block_s = AD.block_means(stream._dec[: stream.n_dec], stream.dec * stream.tau0)
    blocks = {"ybar": ybar, "block_s": block_s,
              "rows_per_block": int(round(block_s / stream.tau0))}  # for the temperature check
    warm = AD.start_transient(ybar, block_s, res.tau_s, res.dev, (res.n_phase - 1) * res.tau0_s,
                              sensor)
    # short excursions of the level (30 s .. a quarter of the record), before the fit: reported
    excursions = EXA.axis_excursions(ybar, block_s, res.tau0_s, sensor, fit)
    if warm.get("trim_s") is not None:  # the self-check names it where it explains the taus
        AD.name_in_check(fit["check"], res.tau_s, warm["share"], AD.warmup_reason(warm), "warmup",
                         AD.warmup_reason_below(warm))
    # a bump the warm-up does not explain: stationary noise, or not? With gaps skipped the
    # block means are those of the rows as recorded (a gap's missing samples have none: the
    # stretches follow one another), so a window holding a gap splices two stretches; the
    # quiet stretch's samples are rows, as --segments takes them
    AD.name_bumps(fit["check"], ybar, block_s, res.tau0_s, fit)
    # ... stationary: does a Gauss-Markov process fit it? (its likelihood-ratio test, with the
    # pooled estimator's covariance where gaps are skipped)
    st_gm = stretch_samples if gapped else None
    gm = AD.gauss_markov(fit, res.tau_s, res.dev, edfs, res.tau0_s, res.n_phase, sensor,
                         stretch_samples=st_gm)
    if AD.gm_added(gm, fit):
        # ... found, and its hump at a bump the check names: the term goes into the joint
        # fit, whose terms, total and self-check are then those of the model with it
        fit = AD.refit_with_gm(fit, gm, sensor, lambda g: F.fit_terms(
            res.tau_s, res.dev, edfs, sensor, tau0=res.tau0_s, n_phase=res.n_phase,
            tones=[{"freq_hz": t["freq_hz"], "amp_si": t["amp_si"]} for t in tones["tones"]],
            stretch_samples=st_gm, gm=g))
        if warm.get("trim_s") is not None:
            AD.name_in_check(fit["check"], res.tau_s, warm["share"], AD.warmup_reason(warm),
                             "warmup", AD.warmup_reason_below(warm))
        AD.name_bumps(fit["check"], ybar, block_s, res.tau0_s, fit)
        AD.name_unexplained(fit["check"], AD.gm_left_reason(fit))
    screening = _screening(stream, sensor, fit, dev0, res.tau0_s, excluded)
    return {"sensor": sensor, "n_samples": int(res.n_phase - 1), "mode": stream.acc.mode,
            **screening, "excursions": excursions, "tones": tones, "warmup": warm,
            "_blocks": blocks,
            "tau_s": res.tau_s, "m": res.m, "stride": res.stride, "n_terms": res.n_terms,
            f"adev_{si}": res.dev, f"adev_{unit}": res.dev * fac,
            f"lo68_{unit}": lo68 * fac, f"hi68_{unit}": hi68 * fac,
            f"lo95_{unit}": lo95 * fac, f"hi95_{unit}": hi95 * fac,
            "alpha": alphas, "edf": edfs, "fit": fit, "piecewise": pw,
            "_si": si, "_unit": unit}


def _open_checked(path: str, axes: list[str]):
    """The recording, checked (rigctl.recording.recording_reader) for the datasets of ``axes``."""
    return open_recording(path, ["imu/time", *sorted({AXES[a][0].lstrip("/") for a in axes})])


def _sample_rate(f, path: str) -> float:
    return sample_rate(f)


#: what to do with spikes (samples > 10 robust sd from their neighbours): report them only,
#: or also replace each by the running median of its neighbours before the deviations
OUTLIER_MODES = ("report", "exclude")


def compute(path: str, axes: list[str], taus: A.TauSpec = 95, exact: bool = False,
            sample_range: tuple[int, int] | None = None,
            progress_stream: Any = None, outliers: str = "report",
            gaps: str = "skip", warmup: str = "report",
            temperature: str = "report",
            when_streaming: Callable[[], Any] | None = None,
            quiet_stretch: bool = True, excursions: str = QS.DEFAULT_EXCURSIONS) -> dict[str, Any]:
    """:func:`compute_once`, and with ``warmup="exclude"``, when a start transient was found
    on any axis (:mod:`rigctl.analysis.allan_drift`), once more without the record's start:
    the longest of the axes' cuts (``trim_s``, each leaving less than a tenth of the curve's
    deviation), the same cut for every axis. Each axis' ``warmup_excluded`` then keeps the
    cut, the transient found before it and the first pass's fitted terms; the result's
    ``warmup`` says which mode ran. Never silent: the cut is in the result and the text.
    With ``temperature="remove"``, the axes whose slow part follows the recorded temperature
    (each axis' ``temperature``) are analysed once more with that term subtracted from their
    samples (:func:`_without_temperature`). ``when_streaming``: called once the first chunk
    of the record is done and the rest streams (the caller's Python work that holds the GIL,
    e.g. an import, then runs beside compiled sums instead of before the first chunk).
    Last, with ``quiet_stretch`` (the default), each axis whose self-check names a run of taus
    not stationary gets ``quiet_stretch``: the terms fitted again on the quiet stretch the
    stationarity test names, beside the whole record's (:mod:`rigctl.analysis.allan_quiet`;
    the whole record's fit and self-check are left as they are). Each axis' short
    excursions (:mod:`rigctl.analysis.allan_excursions`) are reported; with
    ``excursions="exclude"`` (the default) those inside a quiet stretch are left out of its
    fit, as gaps handled by ``gaps`` (``"report"``: kept in it) (:func:`rigctl.analysis.allan_quiet.add_quiet_stretches`).
    The analysis runs with OpenBLAS at one thread (in this thread and the workers'), so that the
    same record gives the same numbers to the last digit on every run and machine."""
    if excursions not in QS.EXCURSION_MODES:
        raise InputError(f"excursions={excursions!r}: choose from {', '.join(QS.EXCURSION_MODES)}")
    if warmup not in AD.WARMUP_MODES:
        raise InputError(f"warmup={warmup!r}: choose from {', '.join(AD.WARMUP_MODES)}")
    if temperature not in AD.TEMPERATURE_MODES:
        raise InputError(f"temperature={temperature!r}: choose from "
                         f"{', '.join(AD.TEMPERATURE_MODES)}")
    with blas_single_thread():  # this thread's share as the workers' (_PriorityPool._work)
        return _compute(path, axes, taus, exact, sample_range, progress_stream, outliers, gaps,
                        warmup, temperature, when_streaming, quiet_stretch, excursions)


def _compute(path: str, axes: list[str], taus: A.TauSpec, exact: bool,
             sample_range: tuple[int, int] | None, progress_stream: Any, outliers: str, gaps: str,
             warmup: str, temperature: str, when_streaming: Callable[[], Any] | None,
             quiet_stretch: bool, excursions: str) -> dict[str, Any]:
    """:func:`compute`'s work, its arguments checked."""
    out = _with_warmup(path, axes, taus, exact, sample_range, progress_stream, outliers, gaps,
                       warmup, when_streaming)
    out["temperature"] = temperature
    if temperature == "remove":
        out = _without_temperature(out, path, axes, taus, exact, progress_stream, outliers, gaps)
    if quiet_stretch:
        corr = {a: r["temperature_removed"]["before"]["correction"] for a, r in out["axes"].items()
                if (r.get("temperature_removed") or {}).get("before", {}).get("correction")}
        QS.add_quiet_stretches(out, lambda ax, rng, c, d=None: compute_once(
            path, ax, taus, exact, rng, progress_stream, outliers, gaps, corrections=c, drop=d),
            corr, excursions, gaps)
    out["excursions_mode"] = excursions
    # the axes' excursions, grouped where they overlap (the axes that moved together), and
    # those inside each quiet stretch
    out["excursions"] = EXA.group(out["axes"])
    for r in out["axes"].values():
        EXA.mark_quiet(r, 1.0 / float(out["sample_rate_hz"]))
    return out


def _without_temperature(out: dict[str, Any], path: str, axes: list[str], taus: A.TauSpec,
                         exact: bool, progress_stream: Any, outliers: str,
                         gaps: str) -> dict[str, Any]:
    """``out`` analysed again over the same range with each axis' temperature term (where one
    was found) subtracted from its samples; each such axis' ``temperature_removed`` keeps the
    term found, the first pass's terms and self-check. ``out`` itself when none was found."""
    corr = {a: r["temperature"]["correction"] for a, r in out["axes"].items()
            if (r.get("temperature") or {}).get("found")}
    if not corr:
        return out
    s0 = int(out["first_sample"])
    again = compute_once(path, axes, taus, exact, (s0, s0 + int(out["n_samples"])),
                         progress_stream, outliers, gaps, corrections=corr)
    for key in ("warmup", "warmup_cut_s", "temperature"):
        if key in out:
            again[key] = out[key]
    for a, r in again["axes"].items():
        first = out["axes"][a]
        if "warmup_excluded" in first:
            r["warmup_excluded"] = first["warmup_excluded"]
        if a in corr:
            r["temperature_removed"] = {"before": first["temperature"],
                                        "summary_before": summary_line(first),
                                        "coefficients_before": first["fit"]["coefficients"],
                                        "check_before": first["fit"]["check"]}
    return again


def _with_warmup(path: str, axes: list[str], taus: A.TauSpec, exact: bool,
                 sample_range: tuple[int, int] | None, progress_stream: Any, outliers: str,
                 gaps: str, warmup: str,
                 when_streaming: Callable[[], Any] | None = None) -> dict[str, Any]:
    """:func:`compute_once`, and with ``warmup="exclude"`` once more after the cut."""
    out = compute_once(path, axes, taus, exact, sample_range, progress_stream, outliers, gaps,
                       when_streaming=when_streaming)
    out["warmup"] = "report"
    if warmup != "exclude":
        return out
    out["warmup"] = "exclude"
    cut = max((r["warmup"].get("trim_s") or 0.0 for r in out["axes"].values()
               if r["warmup"].get("detected")), default=0.0)
    if cut <= 0:
        return out
    fs = out["sample_rate_hz"]
    n_cut = int(math.ceil(cut * fs))
    s0 = int(out["first_sample"])
    s1 = s0 + int(out["n_samples"])  # rows (a gap's missing samples have none)
    if s1 - (s0 + n_cut) < MIN_SAMPLES or n_cut > (s1 - s0) // 2:
        raise InputError(f"{path}: the start transient would need the first {cut:.0f} s cut, "
                         f"more than half of the analysed range ({(s1 - s0) / fs:.0f} s)",
                         hint="record longer, or analyse without --warmup exclude (the "
                              "transient is then reported and named by the self-check)")
    again = compute_once(path, axes, taus, exact, (s0 + n_cut, s1), progress_stream, outliers, gaps)
    again["warmup"] = "exclude"
    again["warmup_cut_s"] = n_cut / fs
    for a, r in again["axes"].items():
        first = out["axes"][a]
        r["warmup_excluded"] = {"trim_s": n_cut / fs, "trim_samples": n_cut,
                                "before": first["warmup"],
                                "summary_before": summary_line(first),
                                "coefficients_before": first["fit"]["coefficients"],
                                "check_before": first["fit"]["check"]}
    return again


def compute_once(path: str, axes: list[str], taus: A.TauSpec = 95, exact: bool = False,
                 sample_range: tuple[int, int] | None = None,
                 progress_stream: Any = None, outliers: str = "report",
                 gaps: str = "skip", corrections: dict | None = None,
                 when_streaming: Callable[[], Any] | None = None,
                 drop: list[tuple[int, int]] | None = None) -> dict[str, Any]:
    """Stream the recording and analyse ``axes`` (IMU samples ``sample_range`` = [first,
    last) if given, else all); raises InputError on invalid input. With ``progress_stream``
    (a console), progress is shown there (a bar on a terminal, a line per 10 s otherwise).
    Every axis is screened on the way (:mod:`rigctl.solvers.allan_checks`): its output step if
    it is quantized, and its spikes, which are reported and, with ``outliers="exclude"``,
    replaced by the running median of their neighbours before they reach the deviations.
    Gaps (dropped samples, :func:`find_gaps`) are never bridged silently: ``gaps="skip"`` (the
    default) sums only the Allan terms that touch no gap, as Stable32 does (each gap-free
    stretch is summed on its own and the sums and term counts added: exact, nothing is
    bridged); ``"refuse"`` raises InputError saying where they are and what to do,
    ``"longest"`` analyses the longest gap-free stretch, ``"bridge"`` treats the samples as
    contiguous; the result's ``gaps`` records which. ``drop``: rows [a, b) of the recording
    left out (excursions, :mod:`rigctl.analysis.allan_excursions`): each is a gap made on
    purpose, skipped as the record's gaps are with ``gaps="skip"`` and bridged (said in
    ``gaps.excluded``) with ``"bridge"``; ``"refuse"`` and ``"longest"`` are the caller's
    (:func:`rigctl.analysis.allan_quiet.add_quiet_stretches`)."""
    if outliers not in OUTLIER_MODES:
        raise InputError(f"outliers={outliers!r}: choose from {', '.join(OUTLIER_MODES)}")
    if gaps not in GAP_MODES:
        raise InputError(f"gaps={gaps!r}: choose from {', '.join(GAP_MODES)}")
    with _open_checked(path, axes) as f:
        fs = _sample_rate(f, path)
        dsets = {name: f[name] for name in {AXES[a][0] for a in axes}}
        n_all = min(d.shape[0] for d in dsets.values())
        s0, s1 = (0, n_all) if sample_range is None else (
            max(0, int(sample_range[0])), min(n_all, int(sample_range[1])))
        n = max(0, s1 - s0)
        if n < MIN_SAMPLES:
            raise InputError(f"{path}: only {n} IMU samples; need at least {MIN_SAMPLES} "
                             "for an Allan analysis (record longer)")
        # the samples' readers (HDF5's chunk index, a Python callback per chunk: ~0.1 s for a
        # 12 h file) are set up on a thread while the gap scan reads the counter (os.preadv and
        # a compiled scan, without the GIL)
        counter = _streamed_counter(f, s0, s1, gaps)
        if counter is not None:  # the gaps are found chunk by chunk while the samples stream
            found = None
            readers = {name: RowReader(f, name) for name in dsets}
        else:
            with ThreadPoolExecutor(1) as setup:
                made = setup.submit(lambda: {name: RowReader(f, name) for name in dsets})
                try:
                    found = find_gaps(f, s0, s1, fs)
                except BaseException:
                    for r in _result(made).values():
                        r.close()
                    raise
                readers = _result(made)
        try:
            return _compute_streamed(path, fs, axes, taus, exact, s0, s1, n, found, readers,
                                     progress_stream, outliers, gaps, corrections, counter,
                                     when_streaming, _clip_drop(drop, s0, s1))
        finally:
            for r in readers.values():
                r.close()
            if counter is not None:
                counter.close()


#: with gaps skipped or bridged, /imu/counter is read and scanned chunk by chunk with the
#: samples (:func:`_stream_chunks`: the main thread reads chunk i + 1's counter rows with its
#: samples, os.preadv and a compiled scan, without the GIL) instead of in a pass of its own
#: before the first chunk (False: :func:`find_gaps` first, as ``refuse`` and ``longest``
#: always do; the same gaps)
STREAMED_GAPS = True


def _streamed_counter(f: Any, s0: int, s1: int, gaps: str) -> RowReader | None:
    """A reader of /imu/counter when its jumps can be found while the samples stream (see
    :data:`STREAMED_GAPS`: gaps skipped or bridged, a counter as long as the range, read with
    os.preadv, the compiled scan), else None (:func:`find_gaps` before the stream)."""
    if not (STREAMED_GAPS and KER.HAVE_NUMBA and gaps in ("skip", "bridge") and s1 - s0 >= 2
            and "/imu/counter" in f and f["/imu/counter"].shape[0] >= s1
            and f["/imu/counter"].ndim == 1):
        return None
    rd = RowReader(f, "/imu/counter")
    if rd.direct is None:
        rd.close()
        return None
    return rd


def _clip_drop(drop: list[tuple[int, int]] | None, s0: int, s1: int) -> list[tuple[int, int]]:
    """The rows to leave out, clipped to [s0, s1), sorted and merged where they touch."""
    out: list[list[int]] = []
    for a, b in sorted((max(s0, int(a)), min(s1, int(b))) for a, b in (drop or ())):
        if b <= a:
            continue
        if out and a <= out[-1][1]:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return [(a, b) for a, b in out]


def kept_stretches(s0: int, s1: int, breaks: list[int] | None, drop: list[tuple[int, int]],
                   split_at_drop: bool = True) -> np.ndarray:
    """Lengths of the stretches of rows [s0, s1) the Allan sums run over: cut at the gap
    ``breaks`` (rows after a gap, gaps skipped) and, with ``split_at_drop``, at each left-out
    window ``drop`` (rows [a, b), not counted); without it the rows on either side of a
    window join (bridged)."""
    cuts = {s0, s1, *(breaks or ())}
    for a, b in drop:
        cuts.update((a, b))
    edges = sorted(c for c in cuts if s0 <= c <= s1)
    out: list[int] = []
    join = False
    for a, b in zip(edges[:-1], edges[1:]):
        if any(da <= a and b <= db for da, db in drop):
            join = not split_at_drop
            continue
        if join and out and a not in (breaks or ()):
            out[-1] += b - a
        else:
            out.append(b - a)
        join = False
    return np.asarray(out, dtype=np.int64)


def _compute_streamed(path: str, fs: float, axes: list[str], taus: A.TauSpec, exact: bool,
                      s0: int, s1: int, n: int, found: list, readers: dict,
                      progress_stream: Any, outliers: str, gaps: str,
                      corrections: dict | None = None,
                      counter: RowReader | None = None,
                      when_streaming: Callable[[], Any] | None = None,
                      drop: list[tuple[int, int]] | None = None) -> dict[str, Any]:
    """:func:`compute` once the gaps are known (``found``) and the readers are open (closed by
    the caller); with ``counter`` (``found`` None; gaps skipped or bridged) the gaps are found
    from its rows chunk by chunk while the samples stream. ``corrections``: per axis, a term
    subtracted from its samples before everything else
    (:func:`rigctl.analysis.allan_drift.correction_at`: the temperature term with
    --temperature remove)."""
    tau0 = 1.0 / fs
    streamed = found is None
    if streamed:
        found = []  # filled by _stream_chunks, in row order
    missing = sum(m for _, m in found)
    gap_info = {"mode": gaps, "count": len(found), "missing_samples": int(missing),
                "largest_samples": int(max((m for _, m in found), default=0)),
                "rows": [int(g) for g, _ in found[:20]]}
    if found and gaps == "refuse":
        big = max(found, key=lambda g: g[1])
        a, b = longest_stretch(found, s0, s1)
        raise InputError(
            f"{path}: {missing} samples missing in {len(found)} gap(s) in the analysed range "
            f"(largest {big[1]} samples = {big[1] * tau0:.3g} s, before row {big[0]}, "
            f"t = {(big[0] - s0) * tau0:.1f} s into it): the Allan deviations need evenly "
            "spaced samples and rigctl does not bridge gaps on its own",
            hint=f"--gaps skip leaves out every Allan term that touches a gap "
                 f"(Stable32); --gaps longest analyses the longest gap-free stretch ({b - a} samples, "
                 f"{(b - a) * tau0 / 3600:.2f} h); --gaps bridge treats the samples as "
                 "contiguous (every tau spanning a gap is then biased)")
    if found and gaps == "longest":
        s0, s1 = longest_stretch(found, s0, s1)
        n = s1 - s0
        gap_info["range_used"] = [int(s0), int(s1)]
        if n < MIN_SAMPLES:
            raise InputError(f"{path}: the longest gap-free stretch has only {n} IMU samples; "
                             f"need at least {MIN_SAMPLES}")
        missing = 0
    breaks = [g for g, _ in found] if gaps == "skip" else None
    drop = _clip_drop(drop, s0, s1) if gaps in ("skip", "bridge") else []
    n_drop = sum(b - a for a, b in drop)
    if drop and n - n_drop < MIN_SAMPLES:
        raise InputError(f"{path}: only {n - n_drop} IMU samples left once the excluded windows "
                         f"are left out; need at least {MIN_SAMPLES}")
    n -= n_drop  # the samples the sums run over
    ms = A.tau_factors(n + 1, taus, "oadev")
    # below A.FAST_MIN_POINTS the sums are exact, as in A.oadev: there they cost milliseconds,
    # while the strides would throw away most of the EDF of phase-noise-dominated taus
    mode = "exact" if exact or n + 1 < A.FAST_MIN_POINTS else "fast"
    # fast mode's tau set (8 factors per octave at most) where it strides, and for 'all'
    # without --exact also where the sums are exact (below 2^20 points): every factor there
    # would be ~5e5 taus for a 2.8 h capture at 100 Hz (6 min 21 s instead of 7.5 s)
    if not isinstance(taus, (list, tuple)) and (mode == "fast" or (taus == "all" and not exact)):
        ms = A.snap_fast(ms)
        ms = ms[ms <= A.max_factor(n + 1, "oadev")]
    streams = {a: _AxisStream(tau0, ms, mode, n) for a in axes}
    # the progress counts the rows read (s1 - s0), the windows left out (``drop``) included:
    # the stream reports the row it has reached, so a total of n (the rows summed) would end
    # above 100 % with a negative time left
    shown = WorkProgress(f"allan {Path(path).name}, {len(axes)} {'axis' if len(axes) == 1 else 'axes'}",
                         s1 - s0, stream=progress_stream, enabled=progress_stream is not None)
    exclude = outliers == "exclude"

    def stretches() -> np.ndarray | None:
        """The gap-free stretches' lengths when gaps are skipped (every gap known: after the
        stream, or once a dataset has had its last chunk, whose read scanned the last of the
        counter), else None; with windows left out (``drop``), the stretches between them."""
        b = ([g for g, _ in found] if gaps == "skip" else None) if streamed else breaks
        if drop:
            return kept_stretches(s0, s1, b, drop, gaps == "skip")
        return np.diff([s0] + b + [s1]) if b else None

    with _switch_interval(SWITCH_INTERVAL_S), _gc_paused(PAUSE_GC):
        return _stream_and_analyse(path, fs, axes, streams, s0, s1, n, shown, readers, exclude,
                                   breaks, corrections, counter, found, streamed, gaps,
                                   gap_info, missing, outliers, when_streaming, stretches, drop)


#: the interpreter's cyclic garbage collector is paused while a record streams and its axes
#: are analysed (re-enabled afterwards, if it was on; False: left alone). Its generation-2
#: collections walk every object of the process -- ~130,000 after the imports of rigctl,
#: numpy, scipy, numba and h5py, more once the results database's modules are imported
#: beside the stream (0.07 s per walk on this machine) -- holding the GIL, and the younger
#: generations' collections run every few hundred Python objects made (numba's dispatch, the
#: fits). The pipeline's arrays are freed by reference counting (no cycles hold them), so
#: nothing waits for the collector; cyclic garbage made meanwhile (none by the pipeline
#: itself) is collected after. Measured on the 12 h x 6-axis file (`rigctl allan`, user
#: CPU, load 14-22): 4.31-4.77 s with the collector, 4.05-4.26 s paused
PAUSE_GC = True

_GC = {"depth": 0, "was_enabled": False}
_GC_LOCK = threading.Lock()


@contextlib.contextmanager
def _gc_paused(pause: bool, promote: bool = False):
    """gc.disable() inside the block (:data:`PAUSE_GC`), the collector re-enabled (if it was
    enabled before the first) when the last of overlapping blocks (analyses on several
    threads) ends; nothing with ``pause`` False. With ``promote`` (given to the outermost
    block: :func:`collector_paused_for_command`), the objects made inside it go into the
    collector's oldest generation when it ends, unexamined (gc.freeze, then gc.unfreeze;
    not when something else holds objects frozen), instead of being walked by the young
    generations' collections that the first allocations after gc.enable() start."""
    if not pause:
        yield
        return
    with _GC_LOCK:
        if _GC["depth"] == 0:
            _GC["was_enabled"] = gc.isenabled()
            gc.disable()
        _GC["depth"] += 1
    try:
        yield
    finally:
        with _GC_LOCK:
            _GC["depth"] -= 1
            if _GC["depth"] == 0:
                if promote and gc.get_freeze_count() == 0:
                    gc.freeze()  # every tracked object: to the permanent generation ...
                    gc.unfreeze()  # ... and from there to the oldest (no collection runs)
                if _GC["was_enabled"]:
                    gc.enable()


def collector_paused_for_command() -> contextlib.AbstractContextManager:
    """For a command that analyses a recording once and then exits (``rigctl allan``): the
    cyclic garbage collector paused (:data:`PAUSE_GC`) for the whole command -- the stream
    and analyses (:func:`compute`, whose own pause then ends nothing), the store and the
    results database -- and the objects made meanwhile moved into its oldest generation
    unexamined when it ends (:func:`_gc_paused` with ``promote``). Without it the first
    allocations after the analysis' pause start a young-generation collection that walks
    every object made during it: ~120,000, most of them the results database's modules
    imported beside the stream (``when_streaming``), 0.04 s of CPU holding the GIL on
    this machine, and a second one (0.03 s) follows during the store. Cyclic garbage made
    meanwhile waits for the next full collection instead (for the command: the process'
    exit), so the stream makes none that holds its buffers (:class:`_Chains`; the test
    test_pipelined_stream_frees_its_buffers_without_the_collector)."""
    return _gc_paused(PAUSE_GC, promote=True)


_SWITCH = {"depth": 0, "saved": 0.0}
_SWITCH_LOCK = threading.Lock()


@contextlib.contextmanager
def _switch_interval(seconds: float | None):
    """sys.setswitchinterval(seconds) inside the block (:data:`SWITCH_INTERVAL_S`), the
    interval before it restored when the last of overlapping blocks (analyses on several
    threads) ends; nothing with None."""
    if seconds is None:
        yield
        return
    with _SWITCH_LOCK:
        if _SWITCH["depth"] == 0:
            _SWITCH["saved"] = sys.getswitchinterval()
            sys.setswitchinterval(seconds)
        _SWITCH["depth"] += 1
    try:
        yield
    finally:
        with _SWITCH_LOCK:
            _SWITCH["depth"] -= 1
            if _SWITCH["depth"] == 0:
                sys.setswitchinterval(_SWITCH["saved"])


def _stream_and_analyse(path: str, fs: float, axes: list[str], streams: dict, s0: int, s1: int,
                        n: int, shown: WorkProgress, readers: dict, exclude: bool,
                        breaks: list[int] | None, corrections: dict | None,
                        counter: RowReader | None, found: list, streamed: bool, gaps: str,
                        gap_info: dict, missing: int, outliers: str,
                        when_streaming: Callable[[], Any] | None,
                        stretches: Callable[[], np.ndarray | None],
                        drop: list[tuple[int, int]] | None = None) -> dict[str, Any]:
    """:func:`_compute_streamed`'s stream (:func:`_stream_chunks`) and the axes' analyses."""
    ids: dict[str, Any] = {}  # axis -> its task of noise IDs on the decimated copy
    heads: dict[str, Any] = {}  # axis -> its early task (head_noise_ids), if one was queued

    def analyse(a: str) -> dict[str, Any]:
        # both queued before this task at a rank no worse (the early one at its dataset's,
        # 0 or 1, the decimated one at this task's): started, so they cannot wait for a
        # worker. Without the early one's wait, an analysis queued by dataset_done could
        # start beside it on the other worker and take the tones and noise IDs again.
        for t in (heads.get(a), ids.get(a)):
            if t is not None:
                _result(t)
        try:
            return analyse_axis(streams[a], AXES[a][2], exclude, stretches(), a)
        finally:
            # its phase copies (head and decimated: ~45 MB per axis of a 12 h x 2 kHz record)
            # go as soon as its analysis is done, not after the slowest axis' (a Gauss-Markov
            # candidate's: minutes, its covariance meshes beside them)
            streams[a] = None

    def queue(group: list[str], rank: int) -> dict[str, Any]:
        """The analyses of axes whose last chunk is summed, at ``rank``; with
        :data:`SPLIT_NOISE_IDS` their decimated noise IDs first, as tasks of their own."""
        if SPLIT_NOISE_IDS and len(group) > 1:
            ids.update({a: pool.submit_at(rank, streams[a].dec_noise_ids) for a in group})
        return {a: pool.submit_at(rank, analyse, a) for a in group}

    early: dict[str, Any] = {}  # axis -> its analysis, queued when its dataset was done

    def dataset_done(group: list[str], head_tasks: dict[str, Any]) -> None:
        # after every chunk task that is queued (the other dataset's)
        heads.update(head_tasks)
        early.update(queue(group, 2))

    with _PriorityPool(WORKERS) as pool:
        _stream_chunks(pool, path, readers, axes, streams, s0, s1, shown,
                       exclude, breaks, corrections,
                       (counter, found, gaps == "skip") if streamed else None, when_streaming,
                       dataset_done if LEAD_DATASET else None, drop or None, gaps == "skip")
        shown.finish()
        if streamed:
            missing = sum(m for _, m in found)
            gap_info.update(count=len(found), missing_samples=int(missing),
                            largest_samples=int(max((m for _, m in found), default=0)),
                            rows=[int(g) for g, _ in found[:20]])
            breaks = [g for g, _ in found] if gaps == "skip" else None
        gaps_bridged = int(missing) if gaps == "bridge" else 0
        stretch_samples = stretches()
        if breaks or (drop and gaps == "skip"):
            gap_info["stretches"] = len(stretch_samples)
            gap_info["longest_stretch_samples"] = int(np.max(stretch_samples))
        if drop:  # windows left out on purpose: gaps of their own, said so
            gap_info["excluded"] = {"windows": len(drop), "samples": int(sum(b - a for a, b in drop)),
                                    "rows": [[int(a), int(b)] for a, b in drop],
                                    "handled": "skipped" if gaps == "skip" else "bridged"}
        out = {"file": Path(path).name, "sample_rate_hz": fs, "n_samples": int(n),
               "first_sample": int(s0), "dropped_samples": gaps_bridged,
               "gaps": gap_info, "outliers": outliers, "axes": {}}
        # the axes' analyses (noise ID, EDF, fits) in parallel too, in axis order (those of
        # a dataset that finished first are queued already)
        futs = {**queue([a for a in axes if a not in early], 0), **early}
        # the fits take longer than the stream on a long record (tens of seconds, minutes with
        # a Gauss-Markov candidate): their own progress, one step per axis
        fits = WorkProgress(f"allan {Path(path).name}, fits", len(axes), unit="axis" if len(axes) == 1 else "axes",
                            stream=shown.stream if shown.enabled else None, enabled=shown.enabled)
        done = []
        for a in axes:
            done.append(_result(futs[a]))
            fits.update(len(done))
        fits.finish()
    for a, r in zip(axes, done):
        out["axes"][a] = r
        streams[a] = None  # free the per-axis buffers
    if drop:  # the block means skip the windows left out: no longer the rows' temperature's
        for r in out["axes"].values():
            r.pop("_blocks", None)
            r["temperature"] = {"found": False, "skipped": "windows left out of the samples: "
                                                         "the block means do not follow the rows"}
    AD.temperature_step(path, int(s0), out["axes"])  # each axis' "temperature" (if recorded)
    return out


def _stream_chunks(pool: _PriorityPool, path: str, readers: dict, axes: list[str],
                   streams: dict, s0: int, s1: int, shown: WorkProgress,
                   exclude: bool = False, breaks: list[int] | None = None,
                   corrections: dict | None = None,
                   scan: tuple[RowReader, list, bool] | None = None,
                   when_streaming: Callable[[], Any] | None = None,
                   dataset_done: Callable[[list[str], dict[str, Any]], Any] | None = None,
                   drop: list[tuple[int, int]] | None = None,
                   drop_breaks: bool = True) -> None:
    """Read [s0, s1) in chunks of CHUNK_ROWS and feed every axis: while the workers check,
    screen (quantization, spikes; with ``exclude`` spikes replaced) and accumulate chunk i,
    this thread reads chunk i + 1 (:class:`rigctl.recording.recording_reader.RowReader`: os.preadv
    from the chunks' offsets, without the GIL, where the layout allows). At most two chunks
    are in memory. ``breaks``: rows that follow a gap (each starts a new gap-free stretch of
    the Allan sums).

    One task per dataset: after the first chunk (see :data:`FUSED`), one compiled pass over
    its rows writes each selected axis' phase into that axis' accumulator and takes the spike
    prefilter's block extremes, the check and the screen follow from them, and the axes'
    sums are queued as one task each; the first chunk, a chunk with a gap and an axis whose
    spikes are replaced go the per-axis way (column copy, check, screen, add).

    ``scan`` = (counter reader, found, skip): the gaps are found here instead of before
    (``breaks`` is then None): each chunk's /imu/counter rows are read and scanned with its
    samples, the gaps appended to ``found``, and with ``skip`` the rows after them break the
    stretches as ``breaks`` would.

    ``drop``: rows [a, b) left out (not added to the sums; the chunks touching one go the
    per-axis way); with ``drop_breaks`` the samples after each start a new stretch, as after
    a gap, else they follow the samples before it (bridged).

    ``dataset_done``: with :data:`PIPELINED`, the chunks of the first axis' dataset go first
    (:func:`_pipelined`) and this is called with a dataset's axes and their early tasks
    (:meth:`_AxisStream.head_noise_ids`, axis -> future, those queued) as soon as its last
    chunk is summed (from a worker; every gap is known by then)."""
    # two read buffers per dataset (chunk i is being fed while chunk i + 1 is read) and one
    # column buffer per axis, reused: no fresh pages (page faults) per chunk
    rows = min(CHUNK_ROWS, max(0, s1 - s0))
    dsets = {name: r.ds for name, r in readers.items()}
    bufs = [{name: np.empty((rows, *d.shape[1:])) for name, d in dsets.items()}
            for _ in range(2)]
    cols = {a: np.empty(rows) for a in axes}
    scratch = {name: np.empty(rows) for name in dsets}  # unselected columns' phase
    tau0 = next(iter(streams.values())).tau0

    all_cuts = np.asarray(sorted(breaks or ()), dtype=np.int64)
    if scan is not None:
        counter, found, skip = scan
        cbuf = np.empty(rows + 1, dtype=counter.ds.dtype)

    def cuts_at(a0: int) -> np.ndarray:
        """The gap breaks of chunk [a0, a1) (at least those in it); with ``scan``, its
        counter rows are read and scanned here (call once per chunk, in chunk order)."""
        if scan is None:
            return all_cuts
        a1 = min(s1, a0 + CHUNK_ROWS)
        # the row before the chunk too: a jump at a0 is a gap before the chunk's first row
        rows = counter.view(max(s0, a0 - 1), a1, cbuf)
        new = counter_jumps_at(rows, max(s0, a0 - 1))
        release(rows)
        found.extend(new)
        return np.asarray([g for g, _ in new] if skip else (), dtype=np.int64)

    def read_rows(name: str, a0: int, k: int) -> np.ndarray | RowPieces:
        """Chunk [a0, a1)'s rows of one dataset: where they lie in the mapped file
        (:meth:`RowReader.view`: the one pass reads them there; :func:`as_array` copies
        them into its buffer k for the rest), else read into that buffer."""
        return readers[name].view(a0, min(s1, a0 + CHUNK_ROWS), bufs[k][name])

    def read(a0: int, k: int) -> tuple[dict, np.ndarray]:
        """Chunk [a0, a1)'s rows of every dataset, and the gap breaks in it."""
        got = {name: read_rows(name, a0, k) for name in readers}
        return got, cuts_at(a0)

    rank = {name: 0 for name in dsets}  # the datasets' tasks' rank on the workers (_pipelined)

    # only the selected axes' columns must be finite (a gyro-only import stores NaN for the rest)
    fin_cols = {name: sorted({AXES[a][1] for a in axes if AXES[a][0] == name}) for name in dsets}
    groups = {name: [a for a in axes if AXES[a][0] == name] for name in dsets}

    drops = list(drop or ())

    def dropped_in(a0: int, a1: int) -> list[tuple[int, int]]:
        """The left-out windows overlapping rows [a0, a1), relative to a0, clipped."""
        return [(max(a, a0) - a0, min(b, a1) - a0) for a, b in drops if a < a1 and b > a0]

    def edges(name: str, a0: int, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The rows of dataset ``name`` just before and just after chunk [a0, a0 + n) that
        the spike screen's windows of its first and last samples reach into (up to
        CHK.SPIKE_WINDOW // 2 each, within [s0, s1)): read here, so that a sample near a
        chunk boundary is judged against the same window as in one pass over the record."""
        lo, hi = CHK.SPIKE_WINDOW // 2, (CHK.SPIKE_WINDOW - 1) // 2
        shape = dsets[name].shape[1:]
        b0, b1 = max(s0, a0 - lo), min(s1, a0 + n + hi)
        pre = readers[name].read(b0, a0, np.empty((a0 - b0, *shape)))
        post = readers[name].read(a0 + n, b1, np.empty((b1 - a0 - n, *shape)))
        return pre, post

    def edge_cols(a: str, ctx: tuple[np.ndarray, np.ndarray], first: int, n: int
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Axis a's samples of :func:`edges`' rows (``first``: the chunk's first row relative
        to s0, ``n`` its rows), with the same correction as the chunk's samples."""
        c = AXES[a][1]
        pre, post = ctx[0][:, c].astype(np.float64), ctx[1][:, c].astype(np.float64)
        if corrections and a in corrections:
            pre -= AD.correction_at(corrections[a], first - pre.size, pre.size)
            post -= AD.correction_at(corrections[a], first + n, post.size)
        return pre, post

    def feed(a: str, block: np.ndarray, col: int, first: int, cuts: np.ndarray,
             ctx: tuple[np.ndarray, np.ndarray]) -> None:
        y = cols[a][: block.shape[0]]
        np.copyto(y, block[:, col])
        if corrections and a in corrections:  # rows relative to s0
            y -= AD.correction_at(corrections[a], first, y.size)
        y = streams[a].screen(y, first, exclude, *edge_cols(a, ctx, first, y.size))
        a0 = s0 + first
        gone = dropped_in(a0, a0 + y.size)
        ends_here = any(b == a0 for _, b in drops)  # a window left out just before the chunk
        if gone or ends_here:
            feed_kept(a, y, a0, cuts, gone, ends_here)
            return
        # rows after a gap (gaps="skip") start a new gap-free stretch
        inside = cuts[(cuts > a0) & (cuts < a0 + y.size)] - a0 if cuts.size else cuts
        if a0 > s0 and cuts.size and bool(np.any(cuts == a0)):
            streams[a].break_stretch()
        prev = 0
        for c in inside.tolist():
            streams[a].add(y[prev:c])
            streams[a].break_stretch()
            prev = c
        streams[a].add(y[prev:] if prev else y)

    def feed_kept(a: str, y: np.ndarray, a0: int, cuts: np.ndarray,
                  gone: list[tuple[int, int]], after_drop: bool) -> None:
        """:func:`feed` for a chunk that holds left-out rows ``gone`` (relative to a0) or
        follows one (``after_drop``): the pieces between them added, each after a break where
        a gap (``cuts``) or, with ``drop_breaks``, a left-out window ends before it."""
        st = streams[a]
        cut_rel = set((cuts[(cuts >= a0) & (cuts < a0 + y.size)] - a0).tolist()) if cuts.size else set()
        edges = sorted({0, y.size, *cut_rel, *(v for g in gone for v in g)})
        for lo, hi in zip(edges[:-1], edges[1:]):
            if any(g0 <= lo and hi <= g1 for g0, g1 in gone):
                after_drop = True
                continue
            if (lo in cut_rel and (lo > 0 or a0 > s0)) or (after_drop and drop_breaks):
                st.break_stretch()
            after_drop = False
            st.add(y[lo:hi])

    def check(name: str, b: np.ndarray, a0: int) -> None:
        check_finite(path, name, b if fin_cols[name] == [0, 1, 2] else b[:, fin_cols[name]], a0)

    def dataset(name: str, b: np.ndarray | RowPieces, a0: int, cuts: np.ndarray) -> list:
        """Check, screen and queue the accumulation of one dataset's axes for this chunk
        (``cuts``: the gap breaks, at least those in it; ``b`` its rows, an array or the
        pieces of the mapped file, copied into one array only where a step needs one: the
        per-axis way, a failed check, a block the spike screen must look into); returns the
        queued tasks."""
        first = a0 - s0
        group = groups[name]
        n = b.shape[0]
        touched = (cuts.size and bool(np.any((cuts >= a0) & (cuts < a0 + n)))) \
            or bool(dropped_in(a0, a0 + n)) or any(b == a0 for _, b in drops)
        if not (FUSED and KER.HAVE_NUMBA and b.ndim == 2 and b.shape[1] == 3 and not touched
                and not (corrections and any(a in corrections for a in group))
                and all(streams[a].takes_phase() for a in group)):
            b = as_array(b)
            check(name, b, a0)  # a bad block must not reach the accumulators
            ctx = edges(name, a0, n)
            return [pool.submit_at(rank[name], feed, a, b, AXES[a][1], first, cuts, ctx)
                    for a in group]
        outs = [scratch[name][:n]] * 3
        x0 = np.zeros(3)
        offs = np.zeros(3)
        for a in group:
            c = AXES[a][1]
            outs[c] = streams[a].phase_target(n)
            x0[c], offs[c] = streams[a].acc.x_last, streams[a].acc.offset
        bs = KER.extremes_block(CHK.SPIKE_WINDOW)
        if isinstance(b, RowPieces):  # the rows where they lie in the file
            bmin, bmax = KER.phase_cols3(b.base, offs, tau0, x0, outs, bs,
                                         (b.lanes, b.starts, b.rows))
        else:
            bmin, bmax = KER.phase_cols3(b, offs, tau0, x0, outs, bs)
        sel = fin_cols[name]
        hi, lo = float(np.max(bmax[sel])), float(np.min(bmin[sel]))
        limit = PLAUSIBLE.get(name.lstrip("/"), np.inf)
        # NaN and infinity propagate into the running sums (x0: each column's last point)
        if not (np.isfinite(x0[sel]).all() and np.isfinite(hi) and np.isfinite(lo)
                and max(hi, -lo) <= limit):
            check(name, as_array(b), a0)  # raises, naming the first bad row (nothing was summed)
        # the spike screen looks at the samples of an axis only where a block may hold a
        # spike (else it finds none: not called); for that, pieces are copied into one array
        # (a chunk shorter than the window: every sample, see CHK.spikes_beyond)
        loud = {a: n < CHK.SPIKE_WINDOW or CHK.may_have_spikes(
            (bmin[AXES[a][1]], bmax[AXES[a][1]]), streams[a].spike_sigma) for a in group}
        if isinstance(b, RowPieces) and any(loud.values()):
            b = b.dense()
        ctx = edges(name, a0, n) if any(loud.values()) else None
        tasks = []
        for a in group:
            c = AXES[a][1]
            y = streams[a].screen_block(b[:, c], first, exclude, (bmin[c], bmax[c]),
                                        *edge_cols(a, ctx, first, n)) if loud[a] else None
            if y is None:
                tasks.append(pool.submit_at(rank[name], streams[a].add_written, n))
            else:  # spikes replaced: the per-axis running sum of the corrected samples
                tasks.append(pool.submit_at(rank[name], streams[a].add, y))
        return tasks

    starts = list(range(s0, s1, CHUNK_ROWS))
    early: dict[str, Any] = {}  # axis -> the head's noise IDs, once every head is complete
    if PIPELINED and len(starts) > 1:
        # the first axis' dataset first (LEAD_DATASET: its tasks go first on the workers)
        order = sorted(dsets, key=lambda nm: min(axes.index(a) for a in groups[nm]))
        if dataset_done is not None:
            rank.update({nm: i for i, nm in enumerate(order)})
        _pipelined(pool, starts, order, read_rows, cuts_at, dataset, streams, groups, rank,
                   s0, s1, shown, early, when_streaming, dataset_done)
        for e in early.values():
            _result(e)
        return
    nxt = read(starts[0], 0) if starts else None
    for i, a0 in enumerate(starts):
        blocks, cuts = nxt
        preps = [pool.submit(dataset, name, b, a0, cuts) for name, b in blocks.items()]
        nxt = read(starts[i + 1], (i + 1) % 2) if i + 1 < len(starts) else None
        for p in preps:
            for t in _result(p):
                _result(t)
        for b in blocks.values():
            release(b)
        del blocks
        shown.update(min(s1, a0 + CHUNK_ROWS) - s0)
        if i == 0 and when_streaming is not None:
            when_streaming()
        if EARLY_NOISE_ID and not early and i + 1 < len(starts) and all(
                st.head_full() for st in streams.values()):
            early = {a: pool.submit(st.head_noise_ids, s1 - s0 + 1) for a, st in streams.items()}
    for e in early.values():
        _result(e)


class _Chains:
    """The state of :func:`_pipelined`'s chains and the callbacks that run them. Methods, not
    functions nested in :func:`_pipelined`: those referred to each other through their
    closures (``launch`` queued ``run``, whose tasks' callback called ``finished``, which
    called ``launch``), a reference cycle that held everything they reached -- the stream's
    read and column buffers, ~84 MB for a 12 h x 6-axis file -- until the cyclic collector ran,
    which ``rigctl allan`` keeps paused to its exit (:func:`collector_paused_for_command`).
    Here the queued tasks and the callbacks refer to the object, and nothing in it to them:
    it and the buffers go when the last task is done."""

    def __init__(self, pool: _PriorityPool, starts: list[int], names: list[str],
                 dataset: Callable, streams: dict, groups: dict, rank: dict, s0: int, s1: int,
                 early: dict[str, Any],
                 dataset_done: Callable[[list[str], dict[str, Any]], Any] | None):
        self.pool, self.starts, self.names, self.dataset = pool, starts, names, dataset
        self.streams, self.groups, self.rank, self.s0, self.s1 = streams, groups, rank, s0, s1
        self.early, self.dataset_done = early, dataset_done
        self.cond = threading.Condition()
        self.ready: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]] = {nm: {} for nm in names}
        self.done = {name: -1 for name in names}  # the last chunk each dataset has finished
        self.busy = {name: False for name in names}
        self.errors: list[BaseException] = []
        self.last = len(starts) - 1
        self.queued_ids = {name: False for name in names}

    def fail(self, e: BaseException) -> None:
        with self.cond:
            self.errors.append(e)
            self.cond.notify_all()

    def launch(self, name: str) -> None:  # under cond
        j = self.done[name] + 1
        if not self.errors and not self.busy[name] and j in self.ready[name]:
            self.busy[name] = True
            b, c = self.ready[name].pop(j)
            self.pool.submit_at(self.rank[name], self.run, name, j, b, c)

    def finished(self, name: str, j: int) -> None:
        if j == self.last and self.dataset_done is not None:  # before the stream is done
            try:
                group = self.groups[name]
                with self.cond:
                    heads = {a: self.early[a] for a in group if a in self.early}
                self.dataset_done(group, heads)
            except BaseException as e:  # noqa: BLE001 - raised again by the reading thread
                self.fail(e)
        with self.cond:
            self.done[name] = j
            self.busy[name] = False
            group = self.groups[name]
            if EARLY_NOISE_ID and not self.queued_ids[name] and j < self.last and all(
                    self.streams[a].head_full() for a in group):  # (before its next chunk's task)
                self.queued_ids[name] = True
                self.early.update({a: self.pool.submit_at(
                    self.rank[name], self.streams[a].head_noise_ids, self.s1 - self.s0 + 1)
                    for a in group})
            self.launch(name)
            self.cond.notify_all()

    def run(self, name: str, j: int, b: np.ndarray, c: np.ndarray) -> None:
        try:
            tasks = self.dataset(name, b, self.starts[j], c)
        except BaseException as e:  # noqa: BLE001 - raised again by the reading thread
            self.fail(e)
            return
        if not tasks:
            release(b)
            self.finished(name, j)
            return
        left = [len(tasks)]
        lock = threading.Lock()

        def one(t: Any) -> None:
            e = t.exception()
            if e is not None:
                self.fail(e)
                return
            with lock:
                left[0] -= 1
                end = left[0] == 0
            if end:
                release(b)  # (its pieces' pages: nothing reads them any more)
                self.finished(name, j)

        for t in tasks:
            t.add_done_callback(one)


def _pipelined(pool: _PriorityPool, starts: list[int], names: list[str], read_rows: Callable,
               cuts_at: Callable, dataset: Callable, streams: dict, groups: dict, rank: dict,
               s0: int, s1: int, shown: WorkProgress, early: dict[str, Any],
               when_streaming: Callable[[], Any] | None = None,
               dataset_done: Callable[[list[str], dict[str, Any]], Any] | None = None) -> None:
    """:func:`_stream_chunks`' loop without a barrier between chunks (:data:`PIPELINED`):
    each dataset's chunks are a chain -- chunk j + 1's task (its one pass, which writes
    after the phase chunk j left in the accumulators) is queued by the callback of the last
    of chunk j's tasks of that dataset, so one dataset's pass runs while the other's sums
    finish instead of both waiting for the slower. This thread only reads, each dataset on
    its own: its chunk j into its buffer j % 2 once it is done with its chunk j - 2 (its
    tasks read nothing of a chunk after they finish), ``names[0]`` first when both can
    (the counter rows of chunk j, for the gaps, with the first dataset's read of chunk j).
    With ``dataset_done`` (:data:`LEAD_DATASET`) the datasets' tasks have the ranks
    ``rank`` on the workers (``names[0]``'s first), so that dataset runs ahead (by at most
    :data:`LEAD_CHUNKS` chunks: it reads no further until the others catch up), and
    ``dataset_done(axes, heads)`` is called as soon as a dataset's last chunk is summed
    (``heads``: its axes' early tasks below, axis -> future, where queued). The same
    tasks on the same data in the same order per axis: the same numbers. The first error
    raised by a task is raised here. ``when_streaming`` is called (here) once every dataset
    has finished the first chunk; a dataset's early noise IDs of the head
    (:data:`EARLY_NOISE_ID`) are queued (at its rank, before its next chunk's task) by the
    first of its chunks after which its heads are complete, if another chunk follows."""
    ch = _Chains(pool, starts, names, dataset, streams, groups, rank, s0, s1, early,
                 dataset_done)
    cond, done, last, errors = ch.cond, ch.done, ch.last, ch.errors
    hook = [when_streaming]
    cuts: dict[int, np.ndarray] = {}  # chunk -> its gap breaks (scanned with its first read)
    nxt = {name: 0 for name in names}  # the next chunk to read, per dataset

    def progress() -> None:  # this thread: the bar, and the hook after the first chunk
        with cond:
            lo = min(done.values())
        if lo >= 0:
            shown.update(min(s1, starts[lo] + CHUNK_ROWS) - s0)
            if hook[0] is not None:
                call, hook[0] = hook[0], None
                call()

    def pick() -> str | None:  # under cond: the dataset to read for next (names' order)
        for k, name in enumerate(names):
            j = nxt[name]
            if j <= last and done[name] >= j - 2 and (
                    k or dataset_done is None
                    or all(done[o] >= j - LEAD_CHUNKS for o in names[1:])):
                return name
        return None

    while True:
        with cond:
            while not errors and pick() is None and any(nxt[nm] <= last for nm in names):
                cond.wait()
            if errors:
                break
            name = pick()
            if name is None:
                break
            j = nxt[name]
        if j not in cuts:  # the first read of chunk j (datasets read their chunks in order)
            cuts[j] = cuts_at(starts[j])
        got = read_rows(name, starts[j], j % 2)
        with cond:
            nxt[name] = j + 1
            ch.ready[name][j] = (got, cuts[j])
            if all(nxt[nm] > j for nm in names):
                cuts.pop(j, None)
            ch.launch(name)
        progress()
    while True:
        with cond:
            if errors or min(done.values()) >= last:
                break
            cond.wait(0.05)
        progress()
    if errors:
        # (the error's traceback holds the frame of the task that raised it, and so the
        # object: the list is emptied, not left to hold the error)
        first = errors[0]
        errors.clear()
        raise first
    progress()


def _counter_gaps(f: Any, s0: int, s1: int) -> int:
    """Samples missing according to /imu/counter in [s0, s1) (0 without a counter)."""
    if "/imu/counter" not in f:
        return 0
    c = f["/imu/counter"]
    if c.shape[0] < s1 or s1 - s0 < 2:
        return 0
    first, last = int(c[s0]), int(c[s1 - 1])
    return max(0, (last - first + 1) - (s1 - s0))


def counter_jumps_at(c: np.ndarray | RowPieces, a: int) -> list[tuple[int, int]]:
    """Gaps in counter rows ``c`` (rows a, a + 1, ... of /imu/counter; an array or the
    pieces of the mapped file, :meth:`RowReader.view`): (row after the gap, samples missing)
    wherever the counter steps by more than 1."""
    if KER.HAVE_NUMBA and isinstance(c, RowPieces) and c.dtype in (np.uint64, np.int64):
        idx, d = KER.counter_jumps(c.base.view(np.int64), pieces=(c.lanes, c.starts, c.rows))
        return [(int(a + i), int(v - 1)) for i, v in zip(idx, d)]
    c = as_array(c)
    if c.dtype == np.uint64:
        c = c.view(np.int64)  # what the cast to int64 gives, without its pass
    if KER.HAVE_NUMBA:
        idx, d = KER.counter_jumps(c)
        return [(int(a + i), int(v - 1)) for i, v in zip(idx, d)]
    d = np.diff(np.asarray(c, dtype=np.int64))
    return [(int(a + i + 1), int(d[i] - 1)) for i in np.flatnonzero(d > 1)]


def find_gaps(f: Any, s0: int, s1: int, fs: float) -> list[tuple[int, int]]:
    """Gaps in the IMU samples [s0, s1): (row after the gap, samples missing) from the jumps of
    /imu/counter, or without a counter from /imu/time steps longer than 1.5 sample intervals."""
    if s1 - s0 < 2:
        return []
    # read in chunks (a day's counter is 0.7 GB, its differences another 0.7 GB), each chunk
    # with the last value of the previous one so that no step is missed
    if "/imu/counter" in f and f["/imu/counter"].shape[0] >= s1:
        rd = RowReader(f, "/imu/counter")
        ds = rd.ds
        starts = list(range(s0, s1 - 1, CHUNK_ROWS))

        def scan(part: list[int]) -> list[tuple[int, int]]:
            out = []
            buf = np.empty(min(CHUNK_ROWS, s1 - s0) + 1, dtype=ds.dtype)
            for a in part:
                out += counter_jumps_at(rd.read(a, min(s1, a + CHUNK_ROWS + 1), buf), a)
            return out

        try:
            if KER.HAVE_NUMBA and rd.direct is not None and len(starts) > 1 and WORKERS > 1:
                # the reads (os.preadv) and the scans (compiled) release the GIL: the two
                # halves of the record on the two cores
                half = (len(starts) + 1) // 2
                with ThreadPoolExecutor(2) as pool:
                    parts = [_result(f) for f in [pool.submit(scan, x) for x in (starts[:half], starts[half:])]]
                return parts[0] + parts[1]
            return scan(starts)
        finally:
            rd.close()
    if "/imu/time" in f and f["/imu/time"].shape[0] >= s1:
        out = []
        ds = f["/imu/time"]
        for a in range(s0, s1 - 1, CHUNK_ROWS):
            dt = np.diff(np.asarray(ds[a: min(s1, a + CHUNK_ROWS + 1)], dtype=np.float64)) * fs
            out += [(int(a + i + 1), int(round(dt[i])) - 1) for i in np.flatnonzero(dt > 1.5)]
        return out
    return []


def longest_stretch(gaps: list[tuple[int, int]], s0: int, s1: int) -> tuple[int, int]:
    """The longest run of rows [a, b) within [s0, s1) with no gap inside."""
    edges = [s0] + [g for g, _ in gaps] + [s1]
    k = int(np.argmax(np.diff(edges)))
    return edges[k], edges[k + 1]


#: what to do with gaps (dropped samples) in the analysed range: skip every Allan term that
#: touches one (Stable32; the default), refuse (say what to do), analyse the longest gap-free
#: stretch, or treat the samples as contiguous
GAP_MODES = ("skip", "refuse", "longest", "bridge")


def _capture_range(f: Any) -> tuple[int, int, str] | None:
    """Sample range of the longest ``capture`` segment (complete preferred), or None."""
    seg = f.get("/segments")
    if seg is None or any(k not in seg for k in ("kind", "first_sample", "last_sample")):
        return None
    kinds = [bytes(k).rstrip(b"\0") for k in seg["kind"][:]]
    first, last = seg["first_sample"][:], seg["last_sample"][:]
    status = ([bytes(s).rstrip(b"\0") for s in seg["status"][:]] if "status" in seg
              else [b"complete"] * len(kinds))
    labels = ([bytes(s).rstrip(b"\0").decode(errors="replace") for s in seg["label"][:]]
              if "label" in seg else [""] * len(kinds))
    cand = [(st == b"complete", int(b) - int(a), int(a), int(b), lab)
            for k, a, b, st, lab in zip(kinds, first, last, status, labels) if k == b"capture"]
    if not cand:
        return None
    best = max(cand)
    return best[2], best[3], best[4]


def table_motion(f: Any, s0: int, s1: int) -> tuple[float, float]:
    """Largest |table rate| (deg/s) and largest angle excursion (deg) over the IMU samples
    [s0, s1), from /table; (0, 0) when the recording has no table data."""
    if any(n not in f for n in ("/table/rate", "/table/time", "/table/angle", "/imu/time")) or s1 <= s0:
        return 0.0, 0.0
    t = f["/imu/time"]
    t0, t1 = float(t[s0]), float(t[s1 - 1])
    tt = f["/table/time"][:]
    sel = (tt >= t0) & (tt <= t1)
    if not sel.any():
        return 0.0, 0.0
    rate = np.degrees(np.abs(f["/table/rate"][:][sel]))
    ang = np.degrees(f["/table/angle"][:][sel])
    rate, ang = rate[np.isfinite(rate)], ang[np.isfinite(ang).all(axis=1)]  # unreadable polls: no motion known
    return (float(rate.max()) if rate.size else 0.0,
            float((ang.max(axis=0) - ang.min(axis=0)).max()) if len(ang) else 0.0)


#: above these the analysed range is not a static capture (deg/s, deg)
STATIC_RATE_DPS, STATIC_ANGLE_DEG = 0.01, 0.01


def choose_range(path: str, axes: list[str], whole: bool = False
                 ) -> tuple[tuple[int, int] | None, str, str]:
    """The IMU sample range to analyse -- the longest capture segment unless ``whole`` -- its
    description, and a warning ('' if none) when the table moved in it. Raises InputError for
    a file that is not a recording with ``axes``."""
    with _open_checked(path, axes) as f:
        rng = None if whole else _capture_range(f)
        s0, s1 = (0, int(f["/imu/time"].shape[0]) if "/imu/time" in f else 0) if rng is None else rng[:2]
        rate, span = table_motion(f, s0, s1)
    where = "whole recording" if rng is None else f"capture segment '{rng[2]}'"
    warn = ""
    if rate > STATIC_RATE_DPS or span > STATIC_ANGLE_DEG:
        warn = (f"the table moved during the analysed range ({where}: up to {rate:.3g} deg/s, "
                f"{span:.3g} deg): an Allan analysis needs a static capture, so these terms are "
                "not the sensor's noise; record one with procedures/allan-overnight.yaml")
    return (None if rng is None else rng[:2]), where, warn


def solve_recording(path: Path, log: Callable[[str, str], Any]) -> None:
    """Solver hook for a procedure's ``solve: [allan]`` step: default analysis (fast mode,
    95 log-spaced taus, all six axes present) of the longest capture segment (whole record
    if it has none), stored in /results/allan; a short summary goes to ``log("info", ...)``.
    """
    import h5py

    path = str(path)
    with h5py.File(path, "r") as f:
        axes = [a for a in AXES if AXES[a][0] in f]
    if not axes:
        log("warning", f"allan: {path} has no /imu/angular_rate or /imu/specific_force")
        return
    rng, where, warn = choose_range(path, axes)
    if warn:
        log("warning", f"allan: {warn}")
    try:
        result = compute(path, axes, 95, False, rng, gaps="skip")  # noted below
    except InputError as exc:
        log("warning", f"allan: not run: {exc}")
        return
    result["segment"] = where
    store(path, result)
    db_line = production.to_database(path, "allan", result, None)
    if db_line:
        log("info", "allan: " + db_line)
    n, fs = result["n_samples"], result["sample_rate_hz"]
    log("info", f"allan: {where}, {n} samples at {fs:g} Hz ({n / fs / 3600:.2f} h); "
                f"results in {path}:/results/allan")
    g = result.get("gaps") or {}
    if g.get("count"):
        log("info", f"allan: {g['missing_samples']} samples missing in {g['count']} gap(s) "
                    "(counter gaps); the Allan terms touching a gap are skipped (Stable32)")
    for a, r in result["axes"].items():
        log("info", f"allan {a}: " + summary_line(r))
        q = r.get("quiet_stretch") or {}
        if q.get("fitted"):
            log("info", f"allan {a}: quiet stretch t = {q['t_s'][0]:.0f}-{q['t_s'][1]:.0f} s (the record "
                        f"is not stationary at {q['run']['tau_tested_s']:.3g} s): " + summary_line(q))
        elif q:
            log("info", f"allan {a}: not stationary at {q['run']['tau_tested_s']:.3g} s; {q['reason']}")
        warns, notes = screening_notes(r)
        for w in warns + check_warnings(r):
            log("warning", f"allan {a}: {w}")
        for t in notes:  # (taus outside the band by chance: in the results and the CLI only)
            log("info", f"allan {a}: {t}")


def default_axes(path: str) -> list[str]:
    """Every axis, or those an import wrote (/meta import_axes: a gyro-only capture stores the
    other columns as NaN)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            got = f["meta"].attrs.get("import_axes", "") if "meta" in f else ""
    except OSError:
        got = ""  # not readable: compute() says why
    got = got.decode() if isinstance(got, bytes) else str(got)
    axes = [a.strip() for a in got.split(",") if a.strip() in AXES]
    return axes or list(AXES)


def gap_message(g: dict[str, Any]) -> str:
    """One line on the gaps of the analysed range and what was done with them ('' if none)."""
    if not g.get("count"):
        return ""
    head = f"{g['missing_samples']} samples missing in {g['count']} gap(s)"
    if g.get("mode") == "longest":
        a, b = g["range_used"]
        return (f"warning: {head}: analysing the longest gap-free stretch, rows {a}..{b - 1} "
                f"({b - a} samples)")
    if g.get("mode") == "skip":
        return (f"note: {head}: the Allan terms touching a gap are skipped (Stable32's gap "
                f"handling; {g['stretches']} gap-free stretches, the longest "
                f"{g['longest_stretch_samples']} samples)")
    return f"warning: {head}, bridged on request (--gaps bridge): taus spanning a gap are biased"


def check_warnings(r: dict[str, Any]) -> list[str]:
    """The fit's self-check as sentences when it fails (the model does not describe the curve:
    chi-square beyond its 99 % point): one per run of taus where the fitted total leaves the
    curve's 95 % band, with the statistic; [] otherwise (see :func:`check_notes`)."""
    check = r["fit"].get("check") or {}
    runs = check.get("outside") or []
    added = AD.gm_added_sentence(r["fit"])
    head = [added] if added else []
    if check.get("ok") or not runs and not check.get("chi2_beyond_99"):
        return head
    what = ("the fitted total (IEEE 952 terms and the Gauss-Markov term)" if added
            else "the fitted IEEE 952 total")
    out = head + chi2_finding(check) + bounds_sentence(check, r.get("sensor", "gyro"))
    if runs and judged(check).get("n_outside_familywise", 1) == 0:  # on the chi-square alone
        out += _check_sentences(check, "the fitted total is outside the 95 % band, at every "
                                "tau within the simultaneous (family-wise) band or 10 % of "
                                "the deviation,", reasons=False)
    elif runs:
        out += _check_sentences(check, f"{what} leaves the curve's 95 % band")
    # (the runs inside a filter's region by less than 10 %: the filter's, not chance)
    return (out + _small_sentence(_without_filter_runs(check, None, ("outside_small",)))
            + _past_sentence(check) + excluded_sentences(check))


def chi2_carrier_text(check: dict) -> str:
    """The run of taus that carries a chi-square beyond its 99 % point, in words ('' when
    the check names none): "tau 64-106 s: the curve 1.24-1.30x above the fit (...)"."""
    c = check.get("chi2_carried_by")
    if not c:
        return ""
    span = (f"tau {c['tau_from_s']:.3g} s" if c["n_taus"] == 1
            else f"tau {c['tau_from_s']:.3g}-{c['tau_to_s']:.3g} s")
    lo, hi = c["data_over_fit_min"], c["data_over_fit_max"]
    side = "above" if c["side"] == "data above" else "below"
    ratio = f"{lo:.3g}x" if f"{lo:.3g}" == f"{hi:.3g}" else f"{lo:.3g}-{hi:.3g}x"
    if hi >= F.NO_TOTAL_RATIO:
        return (f"{span}: the curve {side} the fit, which has no total there (every term is a "
                f"bound) ({c['n_taus']} taus, chi-square {c['chi2']:.4g} of the whole, "
                f"{100 * c['chi2_share']:.0f} %)")
    return (f"{span}: the curve {side} the fit, its deviation {ratio} the fitted total's "
            f"({c['n_taus']} taus, chi-square {c['chi2']:.4g} of the whole, "
            f"{100 * c['chi2_share']:.0f} %)")


def judged(check: dict) -> dict:
    """The statistic the self-check decides on: that of the completed total (the resolved
    terms plus the bounded ones within their bounds, ``completed``) where the check has one,
    else the check's own (chi2, dof, p_value, n_outside_familywise)."""
    return check.get("completed") or check


def chi2_finding(check: dict) -> list[str]:
    """A chi-square beyond its 99 % point as one sentence: a finding, never a pass, with the
    run of taus that carries it; [] when the chi-square is within its 99 % point."""
    if not check.get("chi2_beyond_99"):
        return []
    carrier = chi2_carrier_text(check)
    st = judged(check)
    fw = ("every informative tau is within its family-wise band, but "
          if st.get("n_outside_familywise", 1) == 0 else "")
    return [f"self-check failed: {fw}the chi-square across taus is beyond its 99 % point "
            f"({st['chi2']:.4g} on {st['dof']} dof, p = {st['p_value']:.2g}): a finding, "
            "not a pass -- the terms do not describe the curve within its statistics"
            + (f"; carried by {carrier}" if carrier else "")]


def _front_sentence(check: dict) -> list[str]:
    """The rising front the fit left out (rigctl.solvers.allan_fit.rising_front), named."""
    f = check.get("front_excluded")
    if not f:
        return []
    return [f"tau {f['tau_from_s']:.3g}-{f['tau_to_s']:.3g} s left out of the fit: the curve "
            f"rises from its shortest tau to a top at {f['top_tau_s']:.3g} s and then falls, "
            "which no IEEE 952 total can (a low-pass filter, or an output dwelling on its "
            f"quantization levels); the terms are fitted from {f['top_tau_s']:.3g} s on"]


def _filter_sentence(check: dict) -> list[str]:
    """The low-pass filter's taus the fit left out (rigctl.solvers.allan_fit.filter_region),
    named with why, and how far below the fitted total the check finds the curve there."""
    f = check.get("filter_excluded")
    if not f:
        return []
    below = [o for o in _in_filter_region(check, "outside") + _in_filter_region(check, "outside_small")
             if o["data_over_fit"] < 1.0]
    named = ""
    if below:
        w = min(below, key=lambda o: o["data_over_fit"])
        named = (f"; the self-check finds the curve below the fitted total there "
                 f"({over_fit_text(w['data_over_fit'], w['worst_tau_s'])}), as a filter makes it")
    return [f"tau {f['tau_from_s']:.3g}-{f['tau_to_s']:.3g} s left out of the fit: the curve "
            "falls faster than tau^-1/2 there, sigma^2 tau rising to the white-noise level by a "
            "deficit that fades per octave (the sensor's low-pass filter, not an IEEE 952 term; "
            f"sigma^2 tau at tau0 x{f['s_over_s_fit'][0]:.3f} of its value at "
            f"{f['tau_to_fit_s']:.3g} s); the terms are fitted from {f['tau_to_fit_s']:.3g} s on"
            + named]


def _in_filter_region(check: dict, key: str) -> list[dict]:
    """The self-check's runs (``key``: ``outside``, ``outside_small``) that lie within the
    filter's region left out of the fit (``filter_excluded``)."""
    f = check.get("filter_excluded")
    if not f:
        return []
    return [o for o in check.get(key) or [] if o["tau_to_s"] <= f["tau_to_s"] * (1 + 1e-9)]


def _without_filter_runs(check: dict, tau: Any, keys: tuple[str, ...]) -> dict:
    """The check with its runs inside the filter's region (``keys``) taken out, and
    ``n_outside`` less their taus (``tau``: the curve's): those are the filter's, named by
    :func:`excluded_sentences`, not chance."""
    out = dict(check)
    for key in keys:
        inside = _in_filter_region(check, key)
        if not inside:
            continue
        out[key] = [o for o in check[key] if o not in inside]
        if key == "outside":
            t = np.asarray(tau if tau is not None else [], dtype=float)
            n_in = sum(int(np.count_nonzero((t >= o["tau_from_s"]) & (t <= o["tau_to_s"])))
                       for o in inside)
            out["n_outside"] = max(check["n_outside"] - n_in, 0)
    return out


def excluded_sentences(check: dict) -> list[str]:
    """The taus left out of the fit (a rising front, a low-pass filter's region), named."""
    return _front_sentence(check) + _filter_sentence(check)


def _spans(runs: list[dict]) -> str:
    return ", ".join(f"{o['tau_from_s']:.3g}" if o["tau_from_s"] == o["tau_to_s"]
                     else f"{o['tau_from_s']:.3g}-{o['tau_to_s']:.3g}" for o in runs)


def _small_sentence(check: dict) -> list[str]:
    """The informative taus where the total is outside the band by less than the departure
    the check reports (10 %), named in one sentence."""
    small = check.get("outside_small") or []
    if not small:
        return []
    worst = max(small, key=lambda o: abs(math.log(o["data_over_fit"])))
    return [f"the fitted total is also outside the 95 % band, by less than "
            f"{100 * check.get('departure_rel', 0.1):.0f} %, at tau {_spans(small)} s (worst "
            f"x{worst['data_over_fit']:.3f} at {worst['worst_tau_s']:.3g} s; chance, or "
            "a mismatch of the model too small for the check to report: filter ripple, a weak "
            "term)"]


def _past_sentence(check: dict) -> list[str]:
    """The taus past the well-determined ones (rigctl.solvers.allan_fit._informative_prefix)
    whose band is informative again and where the total leaves it: not judged, named."""
    past = check.get("outside_past_prefix") or []
    if not past:
        return []
    worst = max(past, key=lambda o: abs(math.log(o["data_over_fit"])))
    return [f"past the well-determined taus (from {check['prefix_end_s']:.3g} s the band is "
            f"wider than x{check.get('informative_ratio', 2.0):g}; where it narrows again, only "
            f"because the noise type read on a handful of averages changed, it is not judged) "
            f"the fitted total is outside the 95 % band at tau {_spans(past)} s (worst "
            f"data/fit x{worst['data_over_fit']:.3f} at {worst['worst_tau_s']:.3g} s)"]


def check_notes(r: dict[str, Any]) -> list[str]:
    """The taus outside the band when the fit as a whole is consistent with the curve (a few of
    ~70 taus outside a 95 % band are expected by chance): named, as a note."""
    check = r["fit"].get("check") or {}
    if not check.get("ok"):  # a chi-square beyond its 99 % point fails too (check_warnings)
        return []
    # the runs inside a filter's region left out of the fit are the filter's (named by
    # excluded_sentences), not chance
    rest = _without_filter_runs(check, r.get("tau_s"), ("outside", "outside_small"))
    runs = rest.get("outside") or []
    head = ("the fitted total is outside the 95 % band, as chance allows for a fit consistent "
            "with the curve,")
    out = bounds_sentence(check, r.get("sensor", "gyro"))
    out += [] if not runs else _check_sentences(rest, head, reasons=False)
    return out + _small_sentence(rest) + _past_sentence(check) + excluded_sentences(check)


def bounds_sentence(check: dict, sensor: str) -> list[str]:
    """The terms reported only as bounds, as the self-check took them (allan_fit.
    _admissible_completion: each in [0, its 95 % upper bound], the one point that follows the
    curve best), in one sentence: where the check passes only thanks to them (``passes_on_bounds``),
    which term at what fraction of its bound follows the curve at which taus; where it fails,
    that the judged total already holds them. [] when no bounded term adds to the total."""
    taken = {t: v for t, v in (check.get("bounded_terms") or {}).items()
             if v.get("fraction_of_bound", 0.0) > 0}
    if not taken:
        return []
    names, units = NC.TERM_NAMES[sensor], NC.FIELD_UNITS[sensor]

    def term(t: str) -> str:
        v = taken[t]
        unit, fac = units["B" if t == "GM" else t]
        name = "Gauss-Markov sigma_GM" if t == "GM" else names[t]
        return (f"{name} {v['value_si'] * fac:.3g} {unit}, {v['fraction_of_bound']:.2f} of its "
                f"bound < {v['upper95_si'] * fac:.3g} {unit}")

    order = sorted(taken, key=lambda t: -taken[t]["fraction_of_bound"])
    within = ("the terms known only as bounds taken within them (the point of [0, bound] "
              "that follows the curve best): " + "; ".join(term(t) for t in order))
    carried = {t: "Gauss-Markov sigma_GM" if t == "GM" else names[t] for t in taken}
    where = ", ".join(f"tau {_spans([o])} s ("
                      + (f"the curve x{o['data_over_fit']:.2f} the resolved terms' total"
                         if o["data_over_fit"] < F.NO_TOTAL_RATIO
                         else "the resolved terms have no total") + f" at {o['worst_tau_s']:.3g} s; "
                      f"carried by {carried.get(o.get('term'), 'the bounds')})"
                      for o in check.get("needs_bounds") or [])
    if check.get("passes_on_bounds"):
        return [f"self-check passed only with {within}"
                + (f" -- they follow the curve at {where}" if where else "")
                + "; the resolved terms alone would fail it (a term present but not resolved: "
                "capture longer to resolve it)"]
    if not check.get("ok"):
        return [f"the total judged includes {within}"
                + (f"; they follow the curve at {where}, where the resolved terms alone leave "
                   "the band" if where else "")]
    if where:
        return [f"the resolved terms alone leave the band at {where}; the check took {within}"]
    return []


def over_fit_text(ratio: float | None, tau_s: float) -> str:
    """A self-check run's data over fitted total in words: "x1.47 at 2.56 s", or that there is
    no total (every term a bound: the check floors it at 1e-300; F.NO_TOTAL_RATIO)."""
    if ratio is not None and ratio < F.NO_TOTAL_RATIO:
        return f"x{ratio:.2f} at {tau_s:.3g} s"
    return "no fitted total there: every term is a bound"


def _check_sentences(check: dict, head: str, reasons: bool = True) -> list[str]:
    runs = check["outside"]
    stat = (f"chi2 {check['chi2']:.4g} on {check['dof']} dof, p = {check['p_value']:.2g}; "
            f"model error {100 * check['model_error_rel']:.0f} % of sigma^2 added"
            if "chi2" in check else "")
    if not reasons:
        spans = ", ".join(f"{o['tau_from_s']:.3g}" if o["tau_from_s"] == o["tau_to_s"]
                          else f"{o['tau_from_s']:.3g}-{o['tau_to_s']:.3g}" for o in runs)
        return [f"{head} at {check['n_outside']} of {check['n_informative']} informative taus "
                f"(tau {spans} s; {stat})"]
    out = [f"{head} at {check['n_outside']} of {check['n_informative']} informative taus ({stat})"]
    for o in runs:
        span = (f"tau {o['tau_from_s']:.3g} s" if o["tau_from_s"] == o["tau_to_s"]
                else f"tau {o['tau_from_s']:.3g}-{o['tau_to_s']:.3g} s")
        r = o["data_over_fit"]
        how = over_fit_text(r, o["worst_tau_s"])
        fb = o.get("followed_by_bound")
        out.append(f"{span}: {o['side']} ({how}); likely {o['likely']}"
                   + (f"; followed by {fb} within its bound (the completed total is inside "
                      "the band there)" if fb else ""))
    return out


#: the output step is mentioned when its rounding noise is at least this share of N^2
QUANT_NOTE_SHARE = 1e-4


def screening_notes(r: dict[str, Any]) -> tuple[list[str], list[str]]:
    """(warnings, notes) about an axis' samples: spikes (a warning: they are in the noise
    unless excluded) and the output quantization (a note; a warning when the noise per sample
    is below half a step, so the rounding is not random)."""
    t_warns, notes = AD.temperature_sentences(r)
    warns = list(AD.warmup_sentences(r)) + t_warns + EXA.sentences(r)
    unit, fac = DEV_UNITS[r["sensor"]]
    sp = r.get("spikes") or {}
    basis = {"samples": ", the samples' own spread: the running-median residual's MAD "
                        "collapses on an output that dwells on its levels",
             "quantization step": ", the output step / sqrt(12)"}.get(sp.get("sd_from", ""), "")
    if sp.get("count"):
        first = ", ".join(f"{t:.2f}" for t in sp["first_times_s"][:5])
        what = (f"{sp['count']} samples ({100 * sp['fraction']:.2g} %) more than "
                f"{sp['threshold_sd']:g} robust sd ({sp['sd_si'] * fac:.3g} {unit}{basis}) from the "
                f"running median of {sp['window_samples']} neighbours, the largest "
                f"{sp['largest_sd']:.0f} sd (first at t = {first} s into the range)")
        if sp.get("excluded"):
            warns.append(f"{what}: replaced by that median before the deviations (--outliers exclude)")
        else:
            warns.append(f"{what}: spikes or outliers, left in the noise the fit sees; "
                         "to leave them out: --outliers exclude")
    elif basis and sp.get("sd_si"):
        notes.append(f"no spikes: no sample more than {sp['threshold_sd']:g} robust sd "
                     f"({sp['sd_si'] * fac:.3g} {unit}{basis}) from the running median of "
                     f"{sp['window_samples']} neighbours")
    for line in tone_notes(r):
        notes.append(line)
    warns += band_warnings(r)
    q = r.get("quantization")
    # a float32 recording is "quantized" too (one ulp, ~1e-9 of N^2): worth no note
    src = (q or {}).get("step_source") or {}
    if q and src.get("kind") == "file_digits" and q.get("share_of_N2", 1.0) < QUANT_NOTE_SHARE \
            and q["random_rounding"]:
        # said once, so that the step in --json is not read as the sensor's LSB
        notes.append(f"samples on a grid of 1e-{src['decimals']} {src['unit']}: the numbers' last "
                     "digit, most likely the resolution the file was written with, not the "
                     "sensor's LSB (its rounding is negligible here)")
    if q and (q.get("share_of_N2", 1.0) >= QUANT_NOTE_SHARE or not q["random_rounding"]):
        n_unit, n_fac = F.FIELD_UNITS[r["sensor"]]["N"]
        step = f"{q[f'step_{unit}']:.4g} {unit}"
        if r["sensor"] == "gyro":
            step += f" = {math.degrees(q['step_si']):.4g} deg/s"
        src = q.get("step_source") or {}
        if src.get("kind") == "file_digits":
            what = (f"the numbers' last digit, 1e-{src['decimals']} {src['unit']}: most likely "
                    "the resolution the file was written with, not the sensor's LSB")
        else:
            what = "the sensor's output step"
        text = (f"output quantized in steps of {step} (read from the samples: {what}): the "
                f"rounding adds white noise N_q = {q['white_N_si'] * n_fac:.3g} {n_unit}")
        if "share_of_N2" in q:
            text += (f", {100 * q['share_of_N2']:.2g} % of the fitted N^2 "
                     f"(N without it: {q['N_without_rounding'] * n_fac:.4g} {n_unit})")
        notes.append(text)
        if not q["random_rounding"]:
            warns.append(f"the noise per sample is {q['noise_per_sample_steps']:.2f} of a step: "
                         "below half a step the rounding is not random and the shortest taus "
                         "describe the quantizer, not the sensor")
    return warns, notes


#: how a vibration band is found, in a note's words (rigctl.solvers.allan_tones.detect_bands)
BAND_MIN_TEXT = (f"at least {TN.BAND_MIN_BINS} contiguous bins beyond the tones' test against "
                 "the local level, tones' lobes left out")


def band_share(r: dict[str, Any]) -> tuple[float, float] | None:
    """The largest share of sigma^2 that the vibration bands' Allan term takes on the axis'
    curve (:func:`rigctl.solvers.allan_tones.tones_avar` of the bands' components), and its
    tau (s); None without bands or a curve."""
    comps = [c for b in ((r.get("tones") or {}).get("bands") or []) for c in b["components"]]
    tau, m = np.asarray(r.get("tau_s", []), dtype=float), np.asarray(r.get("m", []), dtype=float)
    dev = np.asarray(r.get(f"adev_{r.get('_si', '')}", []), dtype=float)
    if not comps or not tau.size or dev.size != tau.size:
        return None
    share = TN.tones_avar(float(tau[0] / m[0]), m, comps) / np.maximum(dev ** 2, 1e-300)
    i = int(np.argmax(share))
    return float(share[i]), float(tau[i])


def tone_notes(r: dict[str, Any]) -> list[str]:
    """One sentence per tone found before the fit (frequency, amplitude in the deviation's
    field unit, the largest share of sigma^2 its Allan term takes, and that it was added to
    the fitted model); [] if none."""
    tn = r.get("tones") or {}
    got = tn.get("tones") or []
    if not got:
        return []
    unit = DEV_UNITS[r["sensor"]][0]
    fs = ", ".join(f"{t['freq_hz']:.4g} Hz, amplitude {t[f'amp_{unit}']:.3g} {unit}" for t in got)
    ft = (r.get("fit") or {}).get("tones") or {}
    share = (f"; together up to {100 * ft['max_share']:.2g} % of sigma^2 (at tau "
             f"{ft['max_share_tau_s']:.3g} s)") if ft else ""
    return [f"{len(got)} tone(s) in the samples ({fs}; Welch periodogram, PSD more than "
            f"{tn['threshold_ratio']:.3g}x the local level, false-alarm probability "
            f"{tn['alpha']:g} per axis){share}: a tone is not an IEEE 952 term, so its Allan "
            "term a^2 sin^4(pi f m tau0) / (m sin(pi f tau0))^2 (amplitude from the spectrum) "
            "is part of the fitted model"]


def band_warnings(r: dict[str, Any]) -> list[str]:
    """One sentence for the vibration bands found before the fit (span, centre, rms in the
    deviation's field unit, the largest share of sigma^2 their Allan term takes) and that
    they are not in the fitted model; [] if none."""
    bands = (r.get("tones") or {}).get("bands") or []
    if not bands:
        return []
    unit = DEV_UNITS[r["sensor"]][0]
    bs = "; ".join(f"{b['f_lo_hz']:.3g}-{b['f_hi_hz']:.3g} Hz: centre {b['freq_hz']:.4g} Hz, "
                   f"rms {b[f'rms_{unit}']:.3g} {unit}, up to {b['peak_ratio']:.3g}x the level"
                   for b in bands)
    bsh = band_share(r)
    where = (f"; its Allan term (from the spectrum) up to {100 * bsh[0]:.2g} % of sigma^2, "
             f"at tau {bsh[1]:.3g} s" if bsh else "")
    return [f"{len(bands)} vibration band(s) in the samples ({bs}; a periodogram of "
            f"{bands[0]['bin_hz']:.3g} Hz bins, {BAND_MIN_TEXT}{where}): narrowband random "
            "power, neither white nor a tone, and NOT in the fitted model; beside its own Allan "
            "term it can hide a low-pass filter's fading from the filter region's read "
            "(docs/allan.md, 'Vibration bands'), so a self-check that fails at the short taus "
            "may be its doing"]


def summary_line(r: dict[str, Any]) -> str:
    """One line per axis: fitted N, B, K with 95 % intervals or upper bounds."""
    parts = []
    co = as_coefficients(r["fit"]["coefficients"])
    for t in ("N", "B", "K"):
        c, unit = in_field_units(co, t)
        if c.resolved:
            lo, hi = c.ci95
            parts.append(f"{t} {c.value:.4g} {unit} [{lo:.4g}, {hi:.4g}]")
        else:
            parts.append(f"{t} < {c.upper95:.4g} {unit}")
    return "; ".join(parts) + " (95 % intervals and upper bounds)"  # the level, said once


def load_noise(f: Any, where: str | Path | None = None) -> dict[str, NoiseCoefficients]:
    """The IEEE 952 coefficients of each axis in an open recording's /results/allan, as
    :func:`store` wrote them ({} when the recording has none). A group of an older layout
    (schema_version 1, before the coefficients were stored) is an InputError: re-run rigctl allan."""
    g = f.get("results/allan")
    if g is None or "json" not in g.attrs:
        return {}
    version = int(g.attrs.get("schema_version", 1))
    if version < SCHEMA_VERSION:
        raise InputError(f"/results/allan has schema_version {version}, before the noise coefficients "
                         f"were stored (version {SCHEMA_VERSION})", where,
                         hint=f"run `rigctl allan {where or 'RECORDING'}` again: it replaces the group")
    axes = json.loads(g.attrs["json"]).get("axes", {})
    return {a: from_json(r["fit"]["coefficients"]) for a, r in axes.items()
            if (r.get("fit") or {}).get("coefficients")}


#: an axis' curve arrays: stored as datasets, not in the JSON summary
CURVE_KEYS = ("tau_s", "m", "stride", "n_terms", "alpha", "edf")


def store(path: str, result: dict[str, Any]) -> None:
    """Write /results/allan (replacing an earlier one) through :func:`rigctl.recording.recorder.write_results`:
    the JSON summary (non-finite numbers kept: an unbounded interval end stays inf) and the curve
    datasets, one group per axis (``/results/allan/gx/tau_s``, ...), each with its units; an
    axis' ``quiet_stretch`` (:mod:`rigctl.analysis.allan_quiet`) in its JSON, its curve in
    ``/results/allan/gx/quiet_stretch/tau_s``, ...)."""
    summary = {"file": result["file"], "sample_rate_hz": result["sample_rate_hz"],
               "n_samples": result["n_samples"],
               "first_sample": result.get("first_sample", 0),
               "dropped_samples": result.get("dropped_samples", 0),
               "segment": result.get("segment", "whole recording"),
               "outliers": result.get("outliers", "report"),
               "warmup": result.get("warmup", "report"),
               "temperature": result.get("temperature", "report"),
               "excursions": jsonable(result.get("excursions") or [], keep_nonfinite=True),
               "excursions_mode": result.get("excursions_mode", "report"),
               **({"verdicts": result["verdicts"]} if result.get("verdicts") else {}),
               "axes": {a: {"sensor": r["sensor"], "mode": r["mode"],
                            **jsonable({k: r.get(k) for k in ("fit", "piecewise", "spikes", "excursions",
                                                              "quantization", "tones", "warmup",
                                                              "warmup_excluded", "temperature",
                                                              "temperature_removed")},
                                       keep_nonfinite=True),
                            **({"quiet_stretch": jsonable(
                                {k: v for k, v in r["quiet_stretch"].items() if k not in CURVE_KEYS
                                 and not k.startswith(("adev_", "lo68_", "hi68_", "lo95_", "hi95_"))},
                                keep_nonfinite=True)} if r.get("quiet_stretch") else {})}
                        for a, r in result["axes"].items()}}
    arrays = {}
    for a, r in result["axes"].items():
        # the whole record's curve in <axis>/, the quiet stretch's (when fitted) in
        # <axis>/quiet_stretch/ (docs/data-format.md)
        q = r.get("quiet_stretch") or {}
        for prefix, c in ((f"{a}/", r), (f"{a}/quiet_stretch/", q if q.get("fitted") else None)):
            if c is None:
                continue
            unit = c["_unit"]
            for key, units in (("tau_s", "s"), ("m", "1"), ("stride", "1"), ("n_terms", "1"),
                               (f"adev_{c['_si']}", c["_si"]), (f"adev_{unit}", unit),
                               (f"lo68_{unit}", unit), (f"hi68_{unit}", unit),
                               (f"lo95_{unit}", unit), (f"hi95_{unit}", unit),
                               ("alpha", "1"), ("edf", "1")):
                arrays[f"{prefix}{key.replace('/', '_per_')}"] = (c[key], units)
    write_results(path, "allan", summary, arrays, schema_version=SCHEMA_VERSION)


