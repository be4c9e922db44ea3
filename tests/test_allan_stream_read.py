"""The streamed pipeline's fast paths give the same numbers as the plain ones:
RowReader (os.preadv from HDF5's chunk offsets) reads what h5py reads, on every layout it
takes and on those it hands to h5py; the one-pass running sum of a dataset's three columns
(rigctl.analysis.allan.FUSED) gives the same deviations, noise types, EDFs, fits and spikes,
bit for bit, as the per-axis path (column copy, check, screen, running sum), with spikes
reported or replaced and with gaps; and a non-finite value in a later chunk is refused with
the same message."""
from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from recording_helpers import write_recording
from rigctl.analysis import allan as AA
from rigctl.analysis import allan_drift as AD
from rigctl.errors import InputError
from rigctl.devices import ImuBlock
from rigctl.recording import recording_reader as RR
from rigctl.recording.recorder import Recorder
from rigctl.recording.recording_reader import RowPieces, RowReader, as_array
from rigctl.solvers import allan_kernels as K


def test_row_reader_equals_h5py(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(0)
    data = rng.standard_normal((10_000, 3))
    p = tmp_path / "layouts.h5"
    with h5py.File(p, "w") as f:
        f.create_dataset("contiguous", data=data)
        f.create_dataset("chunked", data=data, chunks=(64, 3), maxshape=(None, 3))
        f.create_dataset("gzip", data=data, chunks=(100, 3), compression="gzip")
        f.create_dataset("partial_width", data=data, chunks=(100, 1))
        f.create_dataset("big_endian", data=data.astype(">f8"), chunks=(64, 3))
        f.create_dataset("counter", data=np.arange(10_000, dtype=np.uint64), chunks=(256,))
        u = f.create_dataset("unwritten", shape=(1000, 3), chunks=(64, 3), dtype="f8")
        u[:100] = 1.0
        # interleaved writes: the chunks of one dataset are not adjacent in the file
        a = f.create_dataset("inter_a", shape=(5000, 3), chunks=(64, 3), dtype="f8")
        b = f.create_dataset("inter_b", shape=(5000, 3), chunks=(64, 3), dtype="f8")
        for s in range(0, 5000, 700):
            e = min(5000, s + 700)
            a[s:e] = data[s:e]
            b[s:e] = -data[s:e]
    direct = {}
    monkeypatch.setattr(RR, "MAP_MIN_RUN_BYTES", 0)  # (short runs: copied by default)
    with h5py.File(p, "r") as f:
        for name in f:
            ds = f[name]
            r = RowReader(f, name)
            direct[name] = r.direct is not None
            buf = np.empty(ds.shape, ds.dtype)
            n = ds.shape[0]
            for a0, a1 in ((0, n), (63, 65), (17, n - 1), (n - 5, n), (640, 960), (3, 3)):
                got = r.read(a0, a1, buf)
                assert got.shape[0] == a1 - a0
                assert np.array_equal(got, ds[a0:a1]), (name, a0, a1)
                # the rows where they lie in the mapped file (or read, where it cannot map)
                v = r.view(a0, a1, np.empty_like(buf))  # (MAP_MIN_RUN_BYTES 0 below)
                assert isinstance(v, RowPieces) == (direct[name] and a1 > a0), name
                assert v.shape == ds[a0:a1].shape and np.array_equal(as_array(v), ds[a0:a1])
                RR.release(v)
            r.close()
    assert direct == {"contiguous": True, "chunked": True, "gzip": False, "partial_width": False,
                      "big_endian": False, "counter": True, "unwritten": False,
                      "inter_a": True, "inter_b": True}


def test_phase_cols3_bit_identical() -> None:
    if not K.HAVE_NUMBA:
        pytest.skip("numba (the fast extra) not installed")
    rng = np.random.default_rng(1)
    blk = rng.standard_normal((10_007, 3)) * [1e-3, 2.0, 5.0] + [0.0, 9.8, -3.0]
    offs = np.array([0.1, 9.79, -3.01])
    x0 = np.array([1e-3, -2.0, 0.5])
    outs = [np.empty(blk.shape[0]) for _ in range(3)]
    start = x0.copy()
    bmin, bmax = K.phase_cols3(blk, offs, 1 / 2000, x0, outs, 32)
    for c in range(3):
        ref = K.phase_chunk(blk[:, c].copy(), offs[c], 1 / 2000, start[c])
        assert np.array_equal(outs[c], ref)
        assert x0[c] == ref[-1]
        pad = np.full(-blk.shape[0] % 32, np.nan)
        cols = np.concatenate((blk[:, c], pad)).reshape(-1, 32)
        assert np.array_equal(bmin[c], np.nanmin(cols, axis=1))
        assert np.array_equal(bmax[c], np.nanmax(cols, axis=1))
    # the same rows as pieces of a byte buffer (ragged lengths, shuffled places, odd byte
    # offsets: HDF5 does not align chunks), read through lanes: the same bits
    n = blk.shape[0]
    cuts = np.concatenate(([0], np.sort(rng.choice(np.arange(1, n), 12, replace=False)), [n]))
    rows = np.diff(cuts)
    raw, off = bytearray(8 * 3 * n + 400), np.empty(rows.size, np.int64)
    cnt = np.arange(n, dtype=np.int64) + 7
    cnt[cuts[3]:] += 4  # a gap at a piece's first row
    cnt[5000:] += 1
    craw, coff = bytearray(8 * n + 400), np.empty(rows.size, np.int64)
    pos = cpos = 3
    for p in rng.permutation(rows.size):
        off[p], coff[p] = pos, cpos
        b = blk[cuts[p]: cuts[p + 1]].tobytes()
        raw[pos: pos + len(b)] = b
        pos += len(b) + int(rng.integers(0, 20))
        b = cnt[cuts[p]: cuts[p + 1]].tobytes()
        craw[cpos: cpos + len(b)] = b
        cpos += len(b) + int(rng.integers(0, 20))
    base = np.ndarray((8, (len(raw) - 7) // 8), np.float64, buffer=bytes(raw), strides=(1, 8))
    x1 = start.copy()
    outs1 = [np.empty(n) for _ in range(3)]
    bmin1, bmax1 = K.phase_cols3(base, offs, 1 / 2000, x1, outs1, 32, (off % 8, off // 8, rows))
    assert all(np.array_equal(u, v) for u, v in zip(outs, outs1))
    assert np.array_equal(x0, x1) and np.array_equal(bmin, bmin1) and np.array_equal(bmax, bmax1)
    cb = np.ndarray((8, (len(craw) - 7) // 8), np.int64, buffer=bytes(craw), strides=(1, 8))
    got = K.counter_jumps(cb, (coff % 8, coff // 8, rows))
    d = np.diff(cnt)
    assert np.array_equal(got[0], np.flatnonzero(d > 1) + 1) and np.array_equal(got[1], d[d > 1])
    assert got[0].tolist() == [cuts[3], 5000]


def _recording(path: Path, n: int, gaps: bool, seed: int = 4, scale: int = 1) -> None:
    """``scale`` > 1: the 160 000-row layout shrunk by that factor (the spikes' and gaps' rows
    and the file's chunk rows divided by it; two adjacent spikes stay adjacent), for a
    same-results test whose CHUNK_ROWS, HEAD_POINTS and DEC_POINTS shrink with it (SCALE)."""
    rng = np.random.default_rng(seed)
    fs = 200.0
    g = rng.standard_normal((n, 3)) * 1e-3 + np.cumsum(rng.standard_normal((n, 3)), 0) * 1e-7
    a = rng.standard_normal((n, 3)) * 2e-3 + [0.0, 0.0, 9.80665]
    for k in (1_000, 45_000, 45_001, 70_123, 100_000, 140_000, 159_990):  # spikes
        k = k // scale if k != 45_001 else 45_000 // scale + 1
        if k >= n:
            continue
        g[k, k % 3] += 0.2
        a[k, (k + 1) % 3] -= 0.5
    idx = np.arange(n, dtype=np.uint64)
    if gaps:
        idx[60_000 // scale:] += 5
        idx[123_457 // scale:] += 1
    write_recording(path, fs, counter=idx, angular_rate=g, specific_force=a,
                    chunk_rows=8192 // scale)


#: the same-results tests' shrink factor: 40 000 rows in 5 000-row chunks (8 chunks, more than
#: the 2 workers; the gaps one at a chunk boundary and one inside a chunk; spikes on chunk
#: boundaries, side by side and 10 rows from the end; each read across the file's 2048-row
#: chunks), a 4096-point head and the phase decimated by 64 -- the 160 000-row layout divided
#: by 4. What they compare (the same numbers from two ways of streaming) does not depend on the
#: record's length; the analyses after the stream (the Gauss-Markov candidate's gapped
#: covariances above all) cost less on the shorter record
SCALE = 4
N_SCALED = 160_000 // SCALE


def _scaled_chunks(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(AA, "CHUNK_ROWS", 20_000 // SCALE)
    monkeypatch.setattr(AA, "HEAD_POINTS", (1 << 14) // SCALE)
    monkeypatch.setattr(AA, "DEC_POINTS", (1 << 12) // SCALE)


def _flat(r: dict) -> dict:
    keys = ("tau_s", "m", "stride", "n_terms", "adev_rad/s", "adev_m/s^2", "alpha", "edf",
            "lo95_deg/h", "lo95_mg")
    out = {k: np.asarray(r[k]) for k in keys if k in r}
    out["spikes"] = (r["spikes"]["count"], r["spikes"]["first_times_s"], r["spikes"]["largest_sd"])
    # the fit's numbers (to rounding: BLAS may split its sums over threads differently)
    co = r["fit"]["coefficients"]
    cs = [getattr(co, t) for t in r["fit"]["terms"]]
    out["fit"] = np.array([v for e in r["fit"]["terms"].values() for k, v in sorted(e.items())
                           if isinstance(v, float)]
                          + [x for c in cs for x in (c.value, *(c.ci68 or ()), *(c.ci95 or ()), c.upper95 or 0.0)])
    out["fit_supported"] = [c.resolved for c in cs]
    return out


@pytest.mark.parametrize("outliers,gaps,axes,exact", [
    ("report", False, list(AA.AXES), False), ("exclude", False, ["gy", "ax", "az"], False),
    ("report", True, list(AA.AXES), False), ("report", False, ["gx", "ay"], True)])
def test_fused_pass_same_results(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                 outliers: str, gaps: bool, axes: list, exact: bool) -> None:
    if not K.HAVE_NUMBA:
        pytest.skip("numba (the fast extra) not installed")
    rec = tmp_path / "r.h5"
    _recording(rec, N_SCALED, gaps, scale=SCALE)
    # the noise ID's copies: a short head and the phase decimated by 64 (taken inside the
    # cascade on the fused path, by a strided pass on the other)
    _scaled_chunks(monkeypatch)
    got = {}
    decs: list = []
    orig = AA.analyse_axis

    def keep_dec(stream, *args):
        assert stream.dec == 64
        decs.append(stream._dec[: stream.n_dec].copy())
        return orig(stream, *args)

    monkeypatch.setattr(AA, "analyse_axis", keep_dec)
    for fused in (False, True):
        monkeypatch.setattr(AA, "FUSED", fused)
        res = AA.compute(str(rec), axes, 95, exact=exact, outliers=outliers)
        got[fused] = {a: _flat(r) for a, r in res["axes"].items()}
        got[fused]["dec"] = [np.array(v) for v in decs]
        decs.clear()
        assert sum(r["spikes"]["count"] for r in res["axes"].values()) >= len(axes)
        if gaps:
            assert res["gaps"]["count"] == 2
    assert len(got[True]["dec"]) == len(axes)
    for u in got[False]["dec"]:  # (the axes are analysed on two threads, in any order)
        assert u.size == N_SCALED // 64 + 1
        assert any(np.array_equal(u, v) for v in got[True]["dec"])
    for a in axes:
        for k, v in got[False][a].items():
            w = got[True][a][k]
            if k == "fit":
                assert np.allclose(v, w, rtol=1e-9, atol=0, equal_nan=True), a
            else:
                assert (np.array_equal(v, w) if isinstance(v, np.ndarray) else v == w), (a, k)


def test_fused_pass_refuses_nan_like_the_plain_path(tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    rec = tmp_path / "nan.h5"
    _recording(rec, 100_000, False)
    with h5py.File(rec, "r+") as f:
        f["imu/specific_force"][77_777, 2] = np.nan
    monkeypatch.setattr(AA, "CHUNK_ROWS", 20_000)
    msgs = []
    for fused in (False, True):
        monkeypatch.setattr(AA, "FUSED", fused)
        with pytest.raises(InputError) as e:
            AA.compute(str(rec), list(AA.AXES), 95)
        msgs.append(str(e.value))
    assert msgs[0] == msgs[1] and "row 77777" in msgs[0]
    # a NaN in a column not analysed does not matter (a gyro-only import stores NaN there)
    monkeypatch.setattr(AA, "FUSED", True)
    res = AA.compute(str(rec), ["ax", "ay", "gz"], 95)
    assert set(res["axes"]) == {"ax", "ay", "gz"}


def test_cascade_same_terms_as_the_strided_levels() -> None:
    """The compiled cascade (fast mode's levels in one pass per chunk) sums the same terms as
    one StridedLevel per stride: equal term counts, sums equal to rounding, for chunks of
    every size (1 point to more than a piece), reading the sums midway and feeding on."""
    if not K.HAVE_NUMBA:
        pytest.skip("numba (the fast extra) not installed")
    from rigctl.solvers import allan as A
    from rigctl.solvers import allan_stream as S

    rng = np.random.default_rng(7)
    n = 300_001
    y = rng.standard_normal(n) * 1e-3 + np.cumsum(rng.standard_normal(n)) * 1e-6 + 0.3
    ms = A.snap_fast(A.tau_factors(n + 1, 60, "oadev"))
    ms = ms[ms <= A.max_factor(n + 1, "oadev")]
    ms = np.union1d(ms, [3, 5, 1000])  # 1000 = 125 x 8: a wide lag at stride 8
    levels: dict[int, list[int]] = {}
    for m in ms:
        s = A.fast_stride(int(m))
        levels.setdefault(s, []).append(int(m) // s)
    x = np.concatenate(([0.0], np.cumsum(y - 0.3))) * 1e-3
    casc = S.Cascade(levels)
    ref = [S.StridedLevel(s, ks) for s, ks in sorted(levels.items())]
    scratch = np.empty(1 << 16)
    pos = 0
    sizes = [1, 2, 7, 20_000, 1, S.Cascade.SUB + 3, 5000, 100_000]
    k = 0
    while pos < x.size:
        c = min(sizes[k % len(sizes)], x.size - pos)
        casc.feed(x[pos: pos + c], pos)
        for lev in ref:
            lev.feed(x[pos: pos + c], pos, scratch)
        pos += c
        k += 1
        if k == 5:
            casc.flush()  # sums read midway; feeding goes on
    casc.flush()
    for lev in ref:
        got, cnt = casc.level_sums(lev.s)
        for lag in lev.ks:
            assert cnt[lag] == lev.counts[lag] == (x.size - 1) // lev.s + 1 - 2 * lag, (lev.s, lag)
            assert abs(got[lag] / lev.sums[lag] - 1) < 1e-13, (lev.s, lag)


def _small_chunks_spying(monkeypatch: pytest.MonkeyPatch, look, scale: int = 1) -> list:
    """Stream in 20,000-row chunks with a 50,000-point head (complete within the third chunk)
    and record ``look(stream)`` for each axis the analysis is handed after the last chunk
    (``scale``: both divided by it, for a record shrunk by it)."""
    monkeypatch.setattr(AA, "CHUNK_ROWS", 20_000 // scale)
    monkeypatch.setattr(AA, "HEAD_POINTS", 50_000 // scale)
    monkeypatch.setattr(AA, "DEC_POINTS", 1 << 12)
    seen: list = []
    orig = AA.analyse_axis

    def spy(stream, *args):
        seen.append(look(stream))
        return orig(stream, *args)

    monkeypatch.setattr(AA, "analyse_axis", spy)
    return seen


def test_early_noise_ids_same_as_after_the_last_chunk(tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """The noise IDs read from the full-resolution head, taken while the record still streams,
    are the ones the analysis takes after the last chunk (and they are used); the early task
    then drops the head (:meth:`_AxisStream._release_head`: the analysis is handed a stream
    without it), with the same noise IDs, EDFs and tones."""
    rec = tmp_path / "r.h5"
    _recording(rec, N_SCALED, True, scale=SCALE)  # (the shrunk layout: see SCALE)
    used = _small_chunks_spying(monkeypatch, lambda stream: (
        len(stream._nid), stream.head_released, stream._head.nbytes), SCALE)
    got = {}
    for early in (False, True):
        monkeypatch.setattr(AA, "EARLY_NOISE_ID", early)
        res = AA.compute(str(rec), ["gx", "az"], 95)
        got[early] = {a: (np.asarray(r["alpha"]), np.asarray(r["edf"]), r["tones"])
                      for a, r in res["axes"].items()}
    assert [u[0] for u in used[:2]] == [0, 0] and min(u[0] for u in used[2:4]) >= 20
    assert [u[1:] for u in used[:4]] == [(False, (50_000 // SCALE + 1) * 8)] * 2 + [(True, 0)] * 2
    for a in got[False]:
        assert np.array_equal(got[False][a][0], got[True][a][0])
        assert np.array_equal(got[False][a][1], got[True][a][1])
        assert got[False][a][2] == got[True][a][2]


def test_head_kept_where_early_noise_ids_are_not_the_analysis(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With a window left out (``drop``: an excursion) the analysis' N is not the one the
    early task took the head's noise IDs for: the head is kept to the analysis, which reads
    it, and the noise IDs and EDFs are those without the early task. (Bridged: skipped, the
    window's two stretches would put a Gauss-Markov candidate's gapped covariances, seconds
    of CPU, into the test.)"""
    rec = tmp_path / "r.h5"
    _recording(rec, N_SCALED, False, scale=SCALE)  # (the shrunk layout: see SCALE)
    seen = _small_chunks_spying(monkeypatch, lambda st: (st.head_released, st._head.nbytes),
                                SCALE)
    got = {}
    for early in (False, True):
        monkeypatch.setattr(AA, "EARLY_NOISE_ID", early)
        r = AA.compute_once(str(rec), ["gx"], 95, gaps="bridge",
                            drop=[(90_000 // SCALE, 91_000 // SCALE)])["axes"]["gx"]
        got[early] = (np.asarray(r["alpha"]), np.asarray(r["edf"]))
    assert seen == [(False, (50_000 // SCALE + 1) * 8)] * 2
    assert np.array_equal(got[False][0], got[True][0])
    assert np.array_equal(got[False][1], got[True][1])




def test_early_tones_same_as_after_the_last_chunk(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """The tone detection on the head (rigctl.analysis.allan.EARLY_TONES), taken with the early
    noise IDs while the record still streams, gives the tones and fit the analysis gets when it
    runs the periodogram after the last chunk, and the early result is the one used."""
    n, fs = 160_000, 200.0
    rng = np.random.default_rng(7)
    t = np.arange(n) / fs
    g = rng.standard_normal((n, 3)) * 1e-3
    g[:, 0] += 2e-3 * np.sin(2 * np.pi * 13.7 * t)  # a tone on gx, well above the noise
    a = rng.standard_normal((n, 3)) * 2e-3 + [0.0, 0.0, 9.80665]
    rec = tmp_path / "tone.h5"
    write_recording(rec, fs, angular_rate=g, specific_force=a, chunk_rows=8192)
    cached = _small_chunks_spying(monkeypatch, lambda stream: stream._tones is not None)
    got = {}
    for early in (False, True):
        monkeypatch.setattr(AA, "EARLY_TONES", early)
        got[early] = AA.compute(str(rec), ["gx", "gy", "az"], 95)["axes"]
    assert cached == [False] * 3 + [True] * 3
    # the analysis of an axis whose dataset finished first (queued while the other dataset
    # still streams) waits for the axis' early task: gx's is held until gx's analysis has
    # been started on the other worker (it then finds the tones taken early, not None)
    made: list = []
    entered, analysed = threading.Event(), threading.Event()
    init, heads, submit_at, spy = (AA._AxisStream.__init__, AA._AxisStream.head_noise_ids,
                                   AA._PriorityPool.submit_at, AA.analyse_axis)

    def making(self, *args):
        made.append(self)
        init(self, *args)

    def held(self, *args):
        if self is made[0]:  # gx (the streams are made in axis order)
            assert entered.wait(60), "gx's analysis never started"
            analysed.wait(0.5)  # (set at once when the analysis does not wait for this)
        heads(self, *args)

    def queued(pool, rank, fn, *args):
        if getattr(fn, "__name__", "") == "analyse" and args == ("gx",):
            def starting(*a):
                entered.set()
                return fn(*a)
            return submit_at(pool, rank, starting, *args)
        return submit_at(pool, rank, fn, *args)

    def looking(stream, *args):
        try:
            return spy(stream, *args)
        finally:
            if stream is made[0]:
                analysed.set()

    monkeypatch.setattr(AA._AxisStream, "__init__", making)
    monkeypatch.setattr(AA._AxisStream, "head_noise_ids", held)
    monkeypatch.setattr(AA._PriorityPool, "submit_at", queued)
    monkeypatch.setattr(AA, "analyse_axis", looking)
    held_back = AA.compute(str(rec), ["gx", "gy", "az"], 95)["axes"]
    assert entered.is_set() and cached[6:] == [True] * 3
    assert held_back["gx"]["tones"] == got[True]["gx"]["tones"]
    tones = got[True]["gx"]["tones"]["tones"]
    assert tones and abs(tones[0]["freq_hz"] - 13.7) < 0.2  # the injected tone was looked for
    assert got[True]["gx"]["tones"]["samples_used"] == 50_000 - 1  # the head: x[0] = 0 + 49999
    for ax in got[False]:
        assert got[False][ax]["tones"] == got[True][ax]["tones"], ax
        u, w = _flat(got[False][ax]), _flat(got[True][ax])
        assert u.keys() == w.keys()
        for k, v in u.items():
            if k == "fit":  # (to rounding, as above: BLAS)
                assert np.allclose(v, w[k], rtol=1e-9, atol=0, equal_nan=True), ax
            else:
                assert (np.array_equal(v, w[k]) if isinstance(v, np.ndarray) else v == w[k]), (ax, k)


@pytest.mark.parametrize("outliers,gaps,axes", [
    ("report", False, list(AA.AXES)), ("exclude", True, ["gy", "ax", "az"]),
    ("report", True, ["gy"])])
def test_pipelined_chunks_same_results(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                       outliers: str, gaps: bool, axes: list) -> None:
    """Each dataset's chunks chained on its own (AA.PIPELINED: no barrier between chunks)
    give the numbers of the loop that waits for every dataset at the end of each chunk, bit
    for bit, with spikes (reported or replaced), gaps skipped and one or both datasets; and
    the early noise IDs of the head are still taken while the record streams."""
    if not K.HAVE_NUMBA:
        pytest.skip("numba (the fast extra) not installed")
    rec = tmp_path / "r.h5"
    _recording(rec, N_SCALED, gaps, scale=SCALE)
    _scaled_chunks(monkeypatch)
    early: list = []
    orig = AA._AxisStream.head_noise_ids
    monkeypatch.setattr(AA._AxisStream, "head_noise_ids",
                        lambda self, n: (early.append(self.n_rate), orig(self, n))[1])
    got = {}
    for pipelined in (False, True):
        monkeypatch.setattr(AA, "PIPELINED", pipelined)
        early.clear()
        res = AA.compute(str(rec), axes, 95, outliers=outliers)
        assert len(early) == len(axes) and max(early) < N_SCALED  # before the last chunk
        got[pipelined] = {a: _flat(r) for a, r in res["axes"].items()}
        assert sum(r["spikes"]["count"] for r in res["axes"].values()) >= len(axes)
    for a in axes:
        for k, v in got[False][a].items():
            w = got[True][a][k]
            assert (np.array_equal(v, w) if isinstance(v, np.ndarray) else v == w), (a, k)


#: s each sum of the slower dataset is held in test_lead_dataset_same_results
LAG_S = 0.05


@pytest.mark.parametrize("lead_chunks,gaps,axes", [
    (1, False, list(AA.AXES)), (3, True, ["az", "gx", "gy"]),
    (100, False, ["ax", "ay", "az", "gx", "gy", "gz"])])
def test_lead_dataset_same_results(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                   lead_chunks: int, gaps: bool, axes: list) -> None:
    """The first axis' dataset running ahead (AA.LEAD_DATASET, by at most AA.LEAD_CHUNKS
    chunks), its axes analysed while the other dataset still streams, gives the numbers of
    the loop that waits for every dataset at the end of each chunk (AA.PIPELINED False),
    bit for bit, with gaps skipped; the lead dataset is never read more than LEAD_CHUNKS
    chunks ahead of the other, and (when it may run ahead over the whole record and the other
    dataset is the slower) its analyses start before the other's last chunk is summed."""
    if not K.HAVE_NUMBA:
        pytest.skip("numba (the fast extra) not installed")
    rec = tmp_path / "r.h5"
    _recording(rec, N_SCALED, gaps, scale=SCALE)
    _scaled_chunks(monkeypatch)
    monkeypatch.setattr(AA, "LEAD_CHUNKS", lead_chunks)
    lead = AA.AXES[axes[0]][0]
    made: list = []  # the axes' streams, in the order of ``axes``
    events: list = []
    orig_init, orig_add, orig_an = (AA._AxisStream.__init__, AA._AxisStream.add_written,
                                    AA.analyse_axis)
    monkeypatch.setattr(AA._AxisStream, "__init__",
                        lambda self, *a: (orig_init(self, *a), made.append(self))[0])
    # (the pipelined run, when the lead may run ahead over the whole record) the other dataset is
    # made the slower one, each of its sums held LAG_S on its worker: the case LEAD_DATASET is
    # for. Of two equally quick datasets either may finish first (the machine's timing: at
    # cbc1ff8 the gyro dataset did, on a CI worker at background priority), and then its axes
    # are rightly analysed first.
    lag = {"on": False}

    def add_written(self, n: int) -> None:
        if lag["on"] and AA.AXES[axes[made.index(self)]][0] != lead:
            time.sleep(LAG_S)
        orig_add(self, n)
        events.append(("sum", self))

    monkeypatch.setattr(AA._AxisStream, "add_written", add_written)
    monkeypatch.setattr(AA, "analyse_axis",
                        lambda st, sensor, *a: (events.append(("analyse", st)),
                                                orig_an(st, sensor, *a))[1])
    reads: list = []
    orig_view = AA.RowReader.view  # (how the stream reads a chunk)
    monkeypatch.setattr(AA.RowReader, "view", lambda self, a, b, out: (
        reads.append(self.ds.name), orig_view(self, a, b, out))[1])
    got = {}
    for pipelined in (False, True):
        monkeypatch.setattr(AA, "PIPELINED", pipelined)
        lag["on"] = pipelined and lead_chunks >= 8
        made.clear()
        events.clear()
        reads.clear()
        res = AA.compute(str(rec), axes, 95, gaps="skip")
        got[pipelined] = {a: _flat(r) for a, r in res["axes"].items()}
    # (the pipelined run) the lead's analyses start before the other dataset's last sum
    ds_of = {id(st): AA.AXES[a][0] for st, a in zip(made, axes)}
    first_an = next(i for i, (k, st) in enumerate(events) if k == "analyse")
    last_other = max(i for i, (k, st) in enumerate(events)
                     if k == "sum" and ds_of[id(st)] != lead)
    if lead_chunks >= 8:  # (a tighter lead: whether they do depends on the timing)
        # (the other dataset's 8 chunks x 3 sums held LAG_S each: ~1.2 s in which the lead's
        # 8 chunks need a few ms of CPU; with LEAD_DATASET False this fails: every analysis
        # waits for the last chunk of both)
        assert ds_of[id(events[first_an][1])] == lead and first_an < last_other
    # the lead dataset is never read more than lead_chunks chunks ahead of the other
    n_read: dict = {}
    for name in reads:
        if name in ("/imu/angular_rate", "/imu/specific_force"):
            n_read[name] = n_read.get(name, 0) + 1
            behind = min((v for k, v in n_read.items() if k != lead), default=0)
            assert name != lead or n_read[lead] - behind <= lead_chunks
    for a in axes:
        for k, v in got[False][a].items():
            w = got[True][a][k]
            assert (np.array_equal(v, w) if isinstance(v, np.ndarray) else v == w), (a, k)


def test_switch_interval_while_streaming(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The GIL switch interval is AA.SWITCH_INTERVAL_S while the record streams and its axes
    are analysed (workers back from a compiled kernel wait less for the GIL while another
    thread runs Python), the caller's interval afterwards, also after an error."""
    import sys

    rec = tmp_path / "r.h5"
    _recording(rec, 40_000, False)
    monkeypatch.setattr(AA, "CHUNK_ROWS", 20_000)
    seen: list = []
    orig = AA.analyse_axis
    monkeypatch.setattr(AA, "analyse_axis", lambda st, *a: (
        seen.append(sys.getswitchinterval()), orig(st, *a))[1])
    before = sys.getswitchinterval()
    try:
        sys.setswitchinterval(0.0123)
        AA.compute(str(rec), ["gx", "az"], 95)
        assert seen and all(abs(v - AA.SWITCH_INTERVAL_S) < 1e-9 for v in seen)
        assert abs(sys.getswitchinterval() - 0.0123) < 1e-9
        monkeypatch.setattr(AA, "analyse_axis", lambda *a: 1 / 0)
        with pytest.raises(ZeroDivisionError):
            AA.compute(str(rec), ["gx"], 95)
        assert abs(sys.getswitchinterval() - 0.0123) < 1e-9
    finally:
        sys.setswitchinterval(before)


def test_gc_paused_while_streaming(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The cyclic garbage collector is off while the record streams and its axes are analysed
    (AA.PAUSE_GC), on again afterwards, also after an error; left off when it was off before;
    and the results are those with the collector running (nothing in the pipeline relies on
    it), bit for bit."""
    import gc

    rec = tmp_path / "r.h5"
    _recording(rec, 40_000, False)
    monkeypatch.setattr(AA, "CHUNK_ROWS", 20_000)
    seen: list = []
    orig = AA.analyse_axis
    monkeypatch.setattr(AA, "analyse_axis", lambda st, *a: (seen.append(gc.isenabled()),
                                                            orig(st, *a))[1])
    was = gc.isenabled()
    try:
        gc.enable()
        paused = AA.compute(str(rec), ["gx", "az"], 95)
        assert seen and not any(seen)
        assert gc.isenabled()
        seen.clear()
        monkeypatch.setattr(AA, "PAUSE_GC", False)
        running = AA.compute(str(rec), ["gx", "az"], 95)
        assert seen and all(seen)
        for a in ("gx", "az"):
            for k in ("tau_s", "adev_rad/s", "adev_m/s^2", "alpha", "edf"):
                if k in paused["axes"][a]:
                    assert np.array_equal(paused["axes"][a][k], running["axes"][a][k]), (a, k)
        monkeypatch.setattr(AA, "PAUSE_GC", True)
        monkeypatch.setattr(AA, "analyse_axis", lambda *a: 1 / 0)
        with pytest.raises(ZeroDivisionError):
            AA.compute(str(rec), ["gx"], 95)
        assert gc.isenabled()
        gc.disable()
        monkeypatch.setattr(AA, "analyse_axis", orig)
        AA.compute(str(rec), ["gx"], 95)
        assert not gc.isenabled()
    finally:
        if was:
            gc.enable()
        else:
            gc.disable()


def _recorder_file(path: Path, n: int, fs: float = 200.0, scale: int = 1) -> None:
    """A recording written by rigctl's Recorder, 1000 rows per flush: its 8192-row chunks of
    the /imu datasets alternate in the file, at byte offsets that are not multiples of 8;
    with spikes and two gaps in the counter (their rows divided by ``scale``)."""
    rng = np.random.default_rng(11)
    g = rng.standard_normal((n, 3)) * 1e-3 + np.cumsum(rng.standard_normal((n, 3)), 0) * 1e-7
    a = rng.standard_normal((n, 3)) * 2e-3 + [0.0, 0.0, 9.80665]
    for k in (1_000, 45_000, 70_123, 100_000, 140_000):
        k //= scale
        g[k, k % 3] += 0.2
        a[k, (k + 1) % 3] -= 0.5
    idx = np.arange(n, dtype=np.uint64)
    idx[60_000 // scale:] += 5
    idx[123_457 // scale:] += 1
    rec = Recorder(path, {"procedure_name": "mapped rows"}, None, imu_rate_hz=fs,
                   flush_interval_s=0.0)
    for s in range(0, n, 1000):
        e = min(n, s + 1000)
        rec.append_imu(ImuBlock(time=idx[s:e] / fs, counter=idx[s:e], specific_force=a[s:e],
                                angular_rate=g[s:e], temperature=np.full(e - s, 25.0)))
    rec.close("complete")


def test_mapped_rows_same_results(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The stream reading the chunks where they lie in the mapped file (RowReader.view: the
    one pass and the gap scan over the pieces of a recorder-written file, whose datasets'
    chunks alternate at odd byte offsets) gives the numbers of the copied reads (MAP_ROWS
    False), bit for bit, with spikes and gaps skipped; a chunk whose
    blocks may hold a spike is copied for the screen, and every piece is released."""
    if not K.HAVE_NUMBA:
        pytest.skip("numba (the fast extra) not installed")
    rec = tmp_path / "rec.h5"
    # 80 000 rows (the spikes' and gaps' rows halved): 4 chunks of 20 000 rows, more than the
    # 2 workers, each read across 3 or 4 of the recorder's 8192-row chunks (the chunk size
    # stays: a view of several pieces is what is compared); the gapped analyses cost less
    _recorder_file(rec, 80_000, scale=2)
    monkeypatch.setattr(AA, "CHUNK_ROWS", 20_000)
    monkeypatch.setattr(AA, "HEAD_POINTS", 1 << 14)
    monkeypatch.setattr(AA, "DEC_POINTS", 1 << 12)
    monkeypatch.setattr(RR, "MAP_MIN_RUN_BYTES", 0)  # (its 8192-row runs: copied by default)
    seen: list = []
    orig_view, orig_dense, orig_rel = RowReader.view, RowPieces.dense, RowPieces.release
    monkeypatch.setattr(RowReader, "view", lambda self, a, b, out: (
        lambda v: (seen.append(["view", v]), v)[1])(orig_view(self, a, b, out)))
    monkeypatch.setattr(RowPieces, "dense", lambda self: (seen.append(["dense", self]),
                                                          orig_dense(self))[1])
    monkeypatch.setattr(RowPieces, "release", lambda self: (seen.append(["release", self]),
                                                            orig_rel(self))[1])
    got = {}
    for mapped in (False, True):
        monkeypatch.setattr(RR, "MAP_ROWS", mapped)
        seen.clear()
        res = AA.compute(str(rec), list(AA.AXES), 95, gaps="skip")
        got[mapped] = {a: _flat(r) for a, r in res["axes"].items()}
        assert res["gaps"]["count"] == 2
        assert sum(r["spikes"]["count"] for r in res["axes"].values()) >= 6
        views = [v for k, v in seen if k == "view"]
        assert all(isinstance(v, RowPieces) == mapped for v in views)
    pieces = [v for k, v in seen if k == "view"]
    assert max(len(v.starts) for v in pieces) >= 3 and any(v.lanes.any() for v in pieces)
    # the first chunk (the per-axis way) and each chunk with a spike were copied, not others
    dense = {id(v) for k, v in seen if k == "dense"}
    assert 0 < len(dense) < len(pieces)
    assert {id(v) for k, v in seen if k == "release"} == {id(v) for v in pieces}
    for a in AA.AXES:
        for k, v in got[False][a].items():
            w = got[True][a][k]
            assert (np.array_equal(v, w) if isinstance(v, np.ndarray) else v == w), (a, k)


def test_pipelined_stream_frees_its_buffers_without_the_collector(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The chained stream (AA.PIPELINED) leaves nothing that holds its chunk buffers once
    compute returns: with the cyclic garbage collector off (as `rigctl allan` keeps it for the
    whole command), every read buffer and every column buffer is freed by reference counting
    (a reference cycle among the chain's callbacks held them, ~84 MB on a 12 h x 6-axis file,
    until the process exit); the results are those of the loop with a barrier, bit for bit."""
    import gc
    import weakref

    rec = tmp_path / "rec.h5"
    _recorder_file(rec, 160_000)
    monkeypatch.setattr(AA, "CHUNK_ROWS", 40_000)
    monkeypatch.setattr(AA, "HEAD_POINTS", 1 << 14)
    monkeypatch.setattr(AA, "DEC_POINTS", 1 << 12)
    refs: list = []
    orig_view, orig_empty = RowReader.view, np.empty

    def view(self, a, b, out):
        refs.append(weakref.ref(out.base if out.base is not None else out))
        return orig_view(self, a, b, out)

    def empty(*a, **k):  # the stream's own buffers: read, column, scratch, counter
        arr = orig_empty(*a, **k)
        f = sys._getframe(1)
        if f.f_code.co_name != "_stream_chunks":  # (its comprehensions' frames)
            f = f.f_back
        if f is not None and f.f_code.co_name == "_stream_chunks":
            refs.append(weakref.ref(arr))
        return arr

    monkeypatch.setattr(RowReader, "view", view)
    got = {}
    was = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        for pipelined in (False, True):
            refs.clear()
            monkeypatch.setattr(AA, "PIPELINED", pipelined)
            monkeypatch.setattr(AA.np, "empty", empty)
            res = AA.compute(str(rec), ["gx", "az"], 95, gaps="skip")
            monkeypatch.setattr(AA.np, "empty", orig_empty)
            # 2 x 2 read buffers, 2 columns, 2 scratch, the counter's
            assert res["gaps"]["count"] == 2 and len(refs) >= 9
            got[pipelined] = {a: _flat(r) for a, r in res["axes"].items()}
            alive = [r() for r in refs if r() is not None]
            assert not alive, (pipelined, [x.shape for x in alive])
    finally:
        if was:
            gc.enable()
    for a in ("gx", "az"):
        for k, v in got[False][a].items():
            w = got[True][a][k]
            assert (np.array_equal(v, w) if isinstance(v, np.ndarray) else v == w), (a, k)


def test_pieces_outlive_their_reader(tmp_path: Path) -> None:
    """Rows viewed in the mapped file stay readable after the reader is closed: an analysis
    abandoned on an error (the task pool cancels what is queued and leaves the tasks in flight
    to end in the background) closed the reader while a task still copied a chunk's pieces, and
    ``mmap.close()`` unmapped the file under them -- a segfault of the whole process (a
    clean-clone CI, test_fused_pass_refuses_nan_like_the_plain_path). Run in a child process,
    so that the old code's crash fails this test instead of killing the test worker."""
    import subprocess
    import sys
    import textwrap

    p = tmp_path / "rows.h5"
    data = np.random.default_rng(7).standard_normal((300_000, 3))
    with h5py.File(p, "w") as f:
        f.create_dataset("rows", data=data)
        f.create_dataset("after", data=np.zeros(4096))  # (the rows not in the file's last bytes)
    code = textwrap.dedent(f"""
        import gc, h5py, numpy as np
        from rigctl.recording import recording_reader as RR
        RR.MAP_MIN_RUN_BYTES = 0
        with h5py.File({str(p)!r}, "r") as f:
            want = f["rows"][1000:250000]
            r = RR.RowReader(f, "rows")
            v = r.view(1000, 250000, np.empty((300000, 3)))
            assert isinstance(v, RR.RowPieces), "not mapped: nothing to check"
            r.close()
            del r
            gc.collect()
            assert np.array_equal(RR.as_array(v), want)
            RR.release(v)
        print("ok")
        """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", (out.returncode, out.stderr[-2000:])


@pytest.mark.parametrize("fused", [False, True])
def test_spikes_at_record_and_chunk_ends(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                         fused: bool) -> None:
    """Spikes on the first two and last two samples of the record and on both sides of a
    chunk boundary are all reported by the streamed screen (chunks of 20 000 rows, both
    pipelines), exactly the flags of one pass of a numpy screen over the whole column with
    the stream's sigma (the median of the window of samples that exist); with the old
    end-padded windows none of them was."""
    if fused and not K.HAVE_NUMBA:
        pytest.skip("numba (the fast extra) not installed")
    n, w = 60_000, 25
    rng = np.random.default_rng(21)
    g = rng.standard_normal((n, 3)) * 1e-3
    a = rng.standard_normal((n, 3)) * 2e-3 + [0.0, 0.0, 9.80665]
    hit = np.array([0, 1, 19_999, 20_000, 40_001, n - 2, n - 1])
    g[hit, 0] += np.where(np.arange(hit.size) % 2, 0.05, -0.05)  # 50 sd
    rec = tmp_path / "r.h5"
    write_recording(rec, 200.0, angular_rate=g, specific_force=a, chunk_rows=8192)
    monkeypatch.setattr(AA, "CHUNK_ROWS", 20_000)
    monkeypatch.setattr(AA, "FUSED", fused)
    sp = AA.compute(str(rec), ["gx"], "octave")["axes"]["gx"]["spikes"]
    y, h = g[:, 0], w // 2
    med = np.empty(n)
    med[h: n - h] = np.median(np.lib.stride_tricks.sliding_window_view(y, w), axis=1)
    for i in [*range(h), *range(n - h, n)]:
        seg = np.sort(y[max(i - h, 0): i + h + 1])
        med[i] = seg[seg.size // 2]
    want = np.flatnonzero(np.abs(y - med) > 10.0 * sp["sd_si"])
    assert np.array_equal(want, hit)
    assert sp["count"] == hit.size
    assert np.allclose(sp["first_times_s"], hit / 200.0, rtol=0, atol=1e-9)


def _one_pass_medians(y: np.ndarray, w: int = 25) -> np.ndarray:
    """The running median of one pass over the whole column: the window i - w // 2 .. i + w // 2,
    cut at the record's ends (the value of rank m // 2 of the m samples there)."""
    n, h = y.size, w // 2
    med = np.empty(n)
    med[h: n - h] = np.median(np.lib.stride_tricks.sliding_window_view(y, w), axis=1)
    for i in [*range(h), *range(n - h, n)]:
        seg = np.sort(y[max(i - h, 0): i + h + 1])
        med[i] = seg[seg.size // 2]
    return med


def _cut_median(y: np.ndarray, i: int, c0: int, c1: int, h: int = 12) -> float:
    """The median of sample i's window cut at its chunk [c0, c1) (the old streamed screen)."""
    seg = np.sort(y[max(i - h, c0): min(i + h + 1, c1)])
    return float(seg[seg.size // 2])


def _oadev(y: np.ndarray, tau0: float, ms: np.ndarray) -> np.ndarray:
    """Fully overlapping Allan deviation of rate samples y at factors ms (numpy, the textbook
    sum: sigma^2 = sum (x[k+2m] - 2 x[k+m] + x[k])^2 / (2 m^2 tau0^2 (N - 2m)), x the phase)."""
    x = np.concatenate(([0.0], np.cumsum(y - y.mean()) * tau0))
    out = []
    for m in ms.tolist():
        d = x[2 * m:] - 2.0 * x[m:-m] + x[: x.size - 2 * m]
        out.append(np.sqrt(np.sum(d * d) / (2.0 * m * m * tau0 * tau0 * d.size)))
    return np.array(out)


@pytest.mark.parametrize("outliers", ["report", "exclude"])
@pytest.mark.parametrize("fused,pipelined,corrected", [
    (False, False, False), (True, True, False), (True, False, False), (False, True, False),
    (False, True, True)])
def test_borderline_spikes_at_every_chunk_boundary_offset(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, fused: bool, pipelined: bool,
        corrected: bool, outliers: str) -> None:
    """A sample within 12 rows of a chunk boundary is judged against its whole 25-sample
    window, as in one pass over the record: borderline spikes at every offset -12 .. +12 from
    a boundary (one per boundary, chunks of 512 rows), each placed halfway between the
    thresholds of its window cut at the chunk and of its whole window (the rows across the
    boundary set 4 sd below or above the spike's side, its own side spaced 0.25 sd apart, so
    the two medians differ by at least 0.25 sd), are flagged exactly where a numpy one-pass
    screen flags them, and with --outliers exclude replaced by the one-pass median (the
    deviations equal the numpy overlapping ADEV of the column so cleaned). A second row of
    boundaries carries clear spikes (both windows flag them) whose cut and whole medians
    differ: their replacements must be the whole window's. Plain and fused paths, chained
    (PIPELINED) or not, the fused chain reading the mapped file's rows; and with a term
    subtracted from the samples (--temperature remove's correction: here +-20 sd zigzagging
    every 8 rows, added to the file's samples), which the rows read across a boundary must
    get too. On the old code (each chunk
    screened on its own) the flags of 24 of the 25 borderline offsets differ."""
    if fused and not K.HAVE_NUMBA:
        pytest.skip("numba (the fast extra) not installed")
    C, w, h, fs = 512, 25, 12, 200.0
    offs = np.arange(-h, h + 1)
    bounds = C * np.arange(2, 2 + 2 * offs.size)  # chunk 0 (sigma) and 1 left alone
    n = int(bounds[-1]) + 2 * C + 10  # a last chunk shorter than the window
    rng = np.random.default_rng(5)
    sd0 = 1e-3
    g = rng.standard_normal((n, 3)) * sd0
    a = rng.standard_normal((n, 3)) * 2e-3 + [0.0, 0.0, 9.80665]
    y = g[:, 0]
    # the stream's sigma: 1.4826 x the MAD of chunk 0's residuals about the whole windows
    r0 = (y - _one_pass_medians(y, w))[:C]
    sigma = 1.4826 * float(np.median(np.abs(r0 - np.median(r0))))
    thr = 10.0 * sigma
    spikes, clear = [], []
    for j, B in enumerate(bounds.tolist()):
        k = int(offs[j % offs.size])
        i = B + k
        own = np.arange(B - 2 * h, B) if k < 0 else np.arange(B, B + 2 * h + 1)
        other = np.arange(B, B + h) if k < 0 else np.arange(B - h, B)
        own = own[own != i]
        y[own] = sigma * 0.25 * (rng.permutation(own.size) - (own.size - 1) / 2.0)
        # (offsets -12 and 11: the one row across has to be below, else it is the window's
        # 25th value, above its median, and leaves it where it was)
        y[other] = (-4.0 if j % 2 or k in (-h, h - 1) else 4.0) * sigma
        y[i] = 1.0  # above everything: its windows' medians do not depend on its value
        c0 = (i // C) * C
        m_cut = _cut_median(y, i, c0, c0 + C)
        m_all = float(np.sort(y[i - h: i + h + 1])[h])
        if k < h:
            assert abs(m_cut - m_all) >= 0.24 * sigma  # the two windows disagree
        if j < offs.size:  # borderline: halfway between the two thresholds (the control
            y[i] = thr + 0.5 * (m_cut + m_all) if k < h else m_all + 1.01 * thr  # k = 12)
        else:  # clear: both flag it, their medians (its replacement) differ
            y[i] = max(m_cut, m_all) + 1.5 * thr
            clear.append(i)
        spikes.append(i)
    y[n - 4] = y[n - 4] + 1.5 * thr  # clear, in the 10-row last chunk
    spikes.append(n - 4)
    clear.append(n - 4)
    med = _one_pass_medians(y, w)
    want = np.flatnonzero(np.abs(y - med) > thr)
    # the construction: every borderline spike at offsets -12 .. 11 is judged differently by
    # the cut window, and nothing else in the column is a spike
    cut_flags = []
    for i in spikes[: offs.size]:
        c0 = (i // C) * C
        cut_flags.append(abs(y[i] - _cut_median(y, i, c0, c0 + C)) > thr)
    one_flags = [i in want for i in spikes[: offs.size]]
    assert [a != b for a, b in zip(cut_flags, one_flags)] == [True] * (offs.size - 1) + [False]
    assert set(want) <= set(spikes) and set(clear) <= set(want)
    rec = tmp_path / "r.h5"
    if corrected:  # the file holds y + the term; the stream subtracts it (as the code does)
        corr = {"rows": np.arange(0, n, 8).tolist(),
                "values": (20.0 * sigma * (-1.0) ** np.arange(0, n, 8)).tolist()}
        term = AD.correction_at(corr, 0, n)
        g = g.copy()
        g[:, 0] = y + term
        y = g[:, 0] - term  # what the screen sees (y to rounding)
        med = _one_pass_medians(y, w)
        assert np.array_equal(np.flatnonzero(np.abs(y - med) > thr), want)  # (rounding)
        stream = AA._compute_streamed

        def with_term(*args, **kw):  # (called with corrections positional, None here)
            args = list(args)
            args[13] = {"gx": corr}
            return stream(*args, **kw)

        monkeypatch.setattr(AA, "_compute_streamed", with_term)
    write_recording(rec, fs, angular_rate=g, specific_force=a, chunk_rows=8192)
    monkeypatch.setattr(AA, "CHUNK_ROWS", C)
    monkeypatch.setattr(AA, "FUSED", fused)
    monkeypatch.setattr(AA, "PIPELINED", pipelined)
    seen: dict = {}
    screening = AA._screening

    def spy(stream, *args):
        seen["idx"] = np.concatenate(stream.spikes) if stream.spikes else np.zeros(0, int)
        seen["size"] = np.concatenate(stream.spike_size) if stream.spike_size else np.zeros(0)
        return screening(stream, *args)

    monkeypatch.setattr(AA, "_screening", spy)
    # the fused chain reads the rows where they lie in the mapped file (RowPieces)
    mapped = fused and pipelined
    monkeypatch.setattr(RR, "MAP_MIN_RUN_BYTES", 0 if mapped else RR.MAP_MIN_RUN_BYTES)
    views: list = []
    orig_view = RowReader.view
    monkeypatch.setattr(RowReader, "view", lambda self, a, b, out: (
        lambda v: (views.append(isinstance(v, RowPieces)), v)[1])(orig_view(self, a, b, out)))
    r = AA.compute(str(rec), ["gx"], "octave", outliers=outliers)["axes"]["gx"]
    assert views and all(v == (mapped and RR.MAP_ROWS and RR._MADVISE is not None)
                         for v in views)
    sp = r["spikes"]
    assert sp["sd_si"] == pytest.approx(sigma, rel=1e-12)
    order = np.argsort(seen["idx"])
    assert np.array_equal(seen["idx"][order], want)
    assert np.allclose(seen["size"][order], np.abs(y - med)[want] / sp["sd_si"], rtol=1e-12)
    assert sp["count"] == want.size
    clean = y.copy()
    if outliers == "exclude":
        clean[want] = med[want]
    ms = np.asarray(r["m"])
    assert np.allclose(np.asarray(r["adev_rad/s"]), _oadev(clean, 1.0 / fs, ms), rtol=1e-9,
                       atol=0)
