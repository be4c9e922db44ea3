"""The compiled exact Allan / Hadamard kernels (rigctl.solvers.allan_kernels) against plain
numpy sums written here, on data with a rate random walk and a large offset."""
import numpy as np
import pytest

from rigctl.solvers import allan as A
from rigctl.solvers import allan_kernels as K

pytestmark = pytest.mark.skipif(not K.HAVE_NUMBA, reason="numba (the 'fast' extra) not installed")


def _data(n, seed=3):
    rng = np.random.default_rng(seed)
    return rng.standard_normal(n) * 1e-3 + 9.80665 + np.cumsum(rng.standard_normal(n)) * 1e-6


def _ref_sums(x, ms, order):
    out = []
    for m in ms:
        if order == 2:
            d = x[2 * m:] - 2.0 * x[m: x.size - m] + x[: x.size - 2 * m]
        else:
            n = x.size - 3 * m
            d = x[3 * m:] - 3.0 * x[2 * m: 2 * m + n] + 3.0 * x[m: m + n] - x[:n]
        out.append(float(np.sum(d * d)) if d.size else 0.0)
    return np.array(out)


@pytest.mark.parametrize("order", [2, 3])
@pytest.mark.parametrize("threads", [1, 2])
def test_diff_sums_every_term(order, threads):
    y = _data(300_001)
    x = np.concatenate(([0.0], np.cumsum(y - y.mean()) * 0.01))
    ms = np.array([1, 2, 3, 7, 16, 17, 100, 999, 4096, 30_000, 70_000, 99_000])
    got = K.diff_sums(x, ms[::-1], order, threads, block=4096)[::-1]  # any order of factors
    ref = _ref_sums(x, ms, order)
    assert np.max(np.abs(got / ref - 1)) < 1e-12


def test_phase_bit_identical_to_numpy():
    y = _data(100_000)
    ref = np.concatenate(([0.0], np.cumsum(y - np.mean(y)) * 0.002))
    assert np.array_equal(K.phase(y, 0.002), ref)


def test_oadev_exact_matches_allantools():
    allantools = pytest.importorskip("allantools")
    y = _data(200_000)
    r = A.oadev(y, 0.01, 40, "rate", mode="exact")
    _, dev, _, _ = allantools.oadev(y, rate=100.0, data_type="freq", taus=r.tau_s)
    assert np.max(np.abs(r.dev / dev - 1)) < 1e-12


def test_streamed_exact_and_cascade_equal_one_shot():
    """The streamed accumulator (chunks, decimation cascade of the strided levels) gives the
    one-shot sums: exact mode all terms, fast mode's non-pyramid factors at their stride."""
    y = _data(400_000)
    x = np.concatenate(([0.0], np.cumsum(y - y[:70_000].mean()) * 0.01))
    ms = np.array([1, 5, 16, 40, 200, 1000, 5000, 33_000])
    for mode in ("exact", "fast"):
        acc = A.OadevAccumulator(0.01, ms, mode)
        for a in range(0, y.size, 70_000):
            acc.add_rate(y[a: a + 70_000])
        r = acc.result()
        for m, s, dev in zip(r.m, r.stride, r.dev):
            xs = x[::s]
            k = m // s
            d = xs[2 * k:] - 2.0 * xs[k:-k] + xs[: xs.size - 2 * k]
            ref = np.sqrt(np.sum(d * d) / (2.0 * (m * 0.01) ** 2 * d.size))
            assert abs(dev / ref - 1) < 1e-11, (mode, m, s)


def test_running_median_equals_scipy_median_filter():
    """The compiled running median (the spike screen's first chunk) gives scipy.ndimage's
    median_filter(mode="nearest") value for value: continuous, quantized (ties) and sparse
    data with zeros, records shorter than the window, windows 1 to 129; a non-finite value
    leaves it to scipy (None)."""
    from scipy.ndimage import median_filter

    rng = np.random.default_rng(11)
    for trial in range(90):
        n, w = int(rng.integers(1, 5000)), int(rng.choice([1, 3, 5, 25, 129]))
        y = rng.standard_normal(n) * 10.0 ** rng.uniform(-4, 2)
        if trial % 3 == 1:
            y = np.round(y / y.std() * 3) / 3 if n > 1 else y  # many equal values
        elif trial % 3 == 2:
            y = np.where(rng.random(n) < 0.6, 0.0, y)  # mostly zeros
        got = K.running_median(y, w)
        assert got is not None and np.array_equal(got, median_filter(y, size=w, mode="nearest")), \
            (trial, n, w)
    y = rng.standard_normal(100)
    assert K.running_median(y, 4) is None  # even windows: scipy's
    for bad in (np.nan, np.inf):
        z = y.copy()
        z[37] = bad
        assert K.running_median(z, 25) is None


def test_spikes_beyond_equals_running_median_screen():
    """The screening's fast path finds exactly the spikes (and medians) of the full running
    median (scipy.ndimage.median_filter) when sigma is known."""
    from rigctl.solvers import allan_checks as C

    rng = np.random.default_rng(7)
    for trial in range(60):
        n, w = int(rng.integers(1, 4000)), int(rng.choice([1, 2, 5, 25]))
        y = rng.standard_normal(n)
        if trial % 3 == 0:
            y = np.round(y * 3) / 3  # quantized: many ties in the windows
        hit = rng.integers(0, n, int(rng.integers(0, 15)))
        y[hit] += rng.choice([-1, 1], hit.size) * rng.uniform(0, 30, hit.size)
        sig, k = float(rng.uniform(0.3, 2.0)), float(rng.choice([1.0, 10.0]))
        idx, med, _ = C.find_spikes(y, sig, k, w)
        got, got_med = C.spikes_beyond(y, sig, k, w)
        assert np.array_equal(idx, got) and np.array_equal(med[idx], got_med)


def test_find_gaps_chunked(tmp_path):
    h5py = pytest.importorskip("h5py")
    from rigctl.analysis import allan as AA

    rng = np.random.default_rng(3)
    c = np.arange(5000, dtype=np.int64)
    for k in list(rng.integers(1, 4999, 25)) + [999, 1000, 2001]:
        c[k:] += int(rng.integers(1, 5))
    with h5py.File(tmp_path / "g.h5", "w") as f:
        f["imu/counter"] = c.astype(np.uint64)
    old = AA.CHUNK_ROWS
    AA.CHUNK_ROWS = 1000  # gaps at and next to chunk edges
    try:
        with h5py.File(tmp_path / "g.h5", "r") as f:
            for s0, s1 in ((0, 5000), (5, 4999), (999, 2002)):
                d = np.diff(c[s0:s1])
                ref = [(s0 + i + 1, int(d[i] - 1)) for i in np.flatnonzero(d > 1)]
                assert AA.find_gaps(f, s0, s1, 100.0) == ref
    finally:
        AA.CHUNK_ROWS = old


def _lag1_numpy(x, m, dmax):
    """Riley & Greenhall's lag-1 noise ID in plain numpy: decimate, remove the mean, r1,
    delta = r1 / (1 + r1), difference until delta < 0.25 or d = dmax. (alpha, d)."""
    z = np.asarray(x[::m], dtype=float)
    d = 0
    while True:
        c = z - z.mean()
        den = float(c @ c)
        r1 = float(c[:-1] @ c[1:]) / den if den > 0 else 0.0
        delta = r1 / (1.0 + r1)
        if delta < 0.25 or d >= dmax or z.size < 3:
            return 2 - int(round(2.0 * delta)) - 2 * d, d
        z = np.diff(z)
        d += 1


def test_lag1_alpha_equals_numpy_steps():
    """The compiled lag-1 noise ID (one pass per differencing order, the differences formed
    on the fly) gives the alpha of the plain numpy steps on power-law phase noise of every
    type from white PM (alpha 2) to alpha -4, decimations 1 to 17, dmax 2 and 3 (Hadamard),
    with an offset, so that every differencing order 0-3 is taken."""
    rng = np.random.default_rng(21)
    orders = set()
    for alpha in (2, 1, 0, -1, -2, -3, -4):
        for trial in range(5):
            n = int(rng.integers(3000, 30000))
            f = np.fft.rfftfreq(n)
            f[0] = 1.0
            spec = (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) \
                * f ** ((alpha - 2) / 2.0)
            spec[0] = 0.0
            x = np.fft.irfft(spec, n) * 10.0 ** rng.uniform(-9, 2) + rng.uniform(-5, 5)
            for m in (1, 2, 3, 8, 17):
                for dmax in (2, 3):
                    want, d = _lag1_numpy(x, m, dmax)
                    orders.add(d)
                    assert K.lag1_alpha(x, m, dmax) == want, (alpha, trial, n, m, dmax)
    assert orders == {0, 1, 2, 3}


def test_compile_garbage_collected_while_the_collector_is_paused():
    """A compilation (a kernel not in numba's cache: the first run after an install) leaves its
    cyclic garbage to the collector; with the collector paused (rigctl allan) it is collected
    at the end of the compilation (rigctl.solvers.allan_kernels_jit._CollectAfterCompile), not
    held to the process' exit beside the stream (3797 objects left for this small function
    without it, 1629 of them of numba's and llvmlite's own types).

    Only the compiler's garbage is counted (objects of numba's and llvmlite's types, from the
    collector's DEBUG_SAVEALL list): the test runs in a pytest worker where threads left by
    other tests may make cyclic garbage of their own meanwhile (21885 objects counted in a CI
    run at 41967f2; 34374 here with a thread making self-referencing lists beside it, none of
    them numba's)."""
    import gc

    from numba import njit

    K.HAVE_NUMBA  # noqa: B018 - imports allan_kernels_jit, which installs the listener
    was = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        @njit  # a new function: compiled here, never from a cache
        def sum_sq(x):  # pragma: no cover - compiled
            s = 0.0
            for v in x:
                s += v * v
            return s

        assert sum_sq(np.arange(4.0)) == 14.0
        gc.set_debug(gc.DEBUG_SAVEALL)  # what the collection finds is kept in gc.garbage
        gc.collect()
    finally:
        gc.set_debug(0)
        if was:
            gc.enable()
    garbage, gc.garbage[:] = list(gc.garbage), []
    compiler = [o for o in garbage
                if type(o).__module__.partition(".")[0] in ("numba", "llvmlite")]
    del garbage
    assert len(compiler) < 50, (len(compiler), compiler[:5])


def test_an_end_without_its_start_does_not_stop_the_collection():
    """The listener registered while a compilation was under way (allan_kernels_jit imported on
    one thread while another compiled) sees that compilation's end without its start; the next
    compilation's garbage is still collected at its end with the collector paused."""
    import gc

    from rigctl.solvers import allan_kernels_jit as J

    listener = J._CollectAfterCompile()
    listener.on_end(None)  # the end of a compilation whose start came before registration
    was = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        listener.on_start(None)
        for _ in range(1000):  # cyclic garbage, as a compilation leaves
            a: list = []
            a.append(a)
        del a
        listener.on_end(None)
        left = gc.collect()
    finally:
        if was:
            gc.enable()
    assert left < 100, left
