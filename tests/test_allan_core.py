"""Exact / fast / streaming overlapping Allan deviation; numerical robustness."""
from __future__ import annotations

import numpy as np
import pytest

from rigctl.solvers import allan as A
from rigctl.solvers import allan_edf as E


def _white(n: int, seed: int, sigma: float = 1.0) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal(n) * sigma


def test_exact_equals_allantools() -> None:
    allantools = pytest.importorskip("allantools")
    fs = 200.0
    y = _white(200_000, 1, 0.01) + 0.3 + np.cumsum(_white(200_000, 2, 1e-5))
    r = A.oadev(y, 1.0 / fs, 40, data_type="rate", mode="exact")
    taus, devs, _, ns = allantools.oadev(y, rate=fs, data_type="freq", taus=r.tau_s)
    np.testing.assert_allclose(taus, r.tau_s, rtol=1e-15)
    np.testing.assert_allclose(r.dev, devs, rtol=1e-12, atol=0)
    assert np.array_equal(r.n_terms, ns)


def test_tau_sets() -> None:
    n = 10_001
    assert A.tau_factors(n, "octave").tolist() == [2 ** k for k in range(12)]
    assert A.tau_factors(n, "decade").tolist() == [1, 2, 4, 10, 20, 40, 100, 200, 400, 1000,
                                                   2000]
    assert A.tau_factors(n, "all").tolist() == list(range(1, 2501))
    m = A.tau_factors(n, 30)
    assert m[0] == 1 and m[-1] == 2500 and np.all(np.diff(m) > 0) and 20 <= m.size <= 30
    assert A.tau_factors(n, [3, 5, 5000, 5001], "oadev").tolist() == [3, 5, 5000]
    with pytest.raises(ValueError):
        A.tau_factors(n, "weekly")


def test_fast_stride_rule() -> None:
    for m in range(1, 5000):
        s = A.fast_stride(m)
        assert m % s == 0 and (s == 1 or 8 * s <= m)
    for m in A.snap_fast(A.tau_factors(8_640_001, 95)):
        assert m < 16 or 16 * A.fast_stride(int(m)) >= m  # stride m/16 .. m/8


def test_streaming_equals_one_shot() -> None:
    y = _white(20_000, 3, 0.02) + 1.5
    ms = A.tau_factors(y.size + 1, "all")[::37]
    exact = A.oadev(y, 0.01, ms, data_type="rate", mode="exact")
    rng = np.random.default_rng(4)
    for mode in ("exact", "fast"):
        acc = A.OadevAccumulator(0.01, ms, mode, offset=float(np.mean(y)))
        a = 0
        while a < y.size:  # random chunk sizes, including single samples
            n = int(rng.choice([1, 7, 1000, 4096, 9000], p=[0.05, 0.05, 0.3, 0.3, 0.3]))
            acc.add_rate(y[a: a + n])
            a += n
        r = acc.result()
        assert np.array_equal(r.m, exact.m)
        if mode == "exact":
            np.testing.assert_allclose(r.dev, exact.dev, rtol=1e-12)
            assert np.array_equal(r.n_terms, exact.n_terms)
        else:  # one-shot fast on the same factors gives the identical strided sums
            x = A.phase_from_rate(y, 0.01)
            for m, s, d in zip(r.m, r.stride, r.dev):
                xs = x[:: s]
                k = m // s
                dd = xs[2 * k:] - 2 * xs[k:-k] + xs[: xs.size - 2 * k]
                ref = np.sqrt(np.mean(dd ** 2) / 2.0) / (m * 0.01)
                assert d == pytest.approx(ref, rel=1e-11)


def test_phase_input_streaming() -> None:
    x = np.cumsum(_white(20_001, 5))
    r1 = A.oadev(x, 1.0, "octave", data_type="phase", mode="exact")
    acc = A.OadevAccumulator(1.0, r1.m, "exact")
    for a in range(0, x.size, 3000):
        acc.add_phase(x[a: a + 3000])
    np.testing.assert_allclose(acc.result().dev, r1.dev, rtol=1e-12)


def test_float32_with_gravity_offset() -> None:
    """A float32 accelerometer axis carrying 1 g: float64 phase with the offset removed."""
    n = 1 << 18
    noise = _white(n, 6, 2e-3)
    y32 = (9.80665 + noise).astype(np.float32)  # what a recorder might store
    truth = y32.astype(np.float64) - 9.80665  # the same samples, offset removed exactly
    ms = A.tau_factors(n + 1, "octave")
    ref = A.oadev(truth, 0.001, ms, data_type="rate", mode="exact")
    for mode in ("exact", "fast"):
        got = A.oadev(y32, 0.001, ms, data_type="rate", mode=mode)
        np.testing.assert_allclose(got.dev, ref.dev, rtol=1e-9)
    acc = A.OadevAccumulator(0.001, ms, "exact")
    for a in range(0, n, 10_000):
        acc.add_rate(y32[a: a + 10_000])
    np.testing.assert_allclose(acc.result().dev, ref.dev, rtol=1e-9)
    # the naive float32 running sum (increments quantized to the sum's ulp) is far off
    xf = np.concatenate(([0.0], np.cumsum(y32, dtype=np.float32))).astype(np.float64)
    naive = A.oadev(xf * 0.001, 0.001, ms, data_type="phase", mode="exact").dev
    assert np.max(np.abs(np.log10(naive / ref.dev))) > 1.0  # > 10x wrong somewhere


@pytest.mark.parametrize("noise", ["white_fm", "rw_fm"])
def test_fast_mode_keeps_degrees_of_freedom(noise: str) -> None:
    """Stride <= m/8 keeps the estimator's scatter: empirical EDF over many seeds matches
    the fully overlapping estimator's (and Greenhall's), while stride m loses it."""
    n, seeds = 1 << 13, 300
    ms = np.array([128, 256, 512])
    exact, fast, nonov = [], [], []
    for seed in range(seeds):
        y = _white(n, 1000 + seed)
        if noise == "rw_fm":
            y = np.cumsum(y)
        x = A.phase_from_rate(y, 1.0)
        acc = A.OadevAccumulator(1.0, ms, "fast")
        acc.add_rate(y)
        fast.append(acc.result().dev ** 2)
        exact.append(A.oadev(y, 1.0, ms, "rate", mode="exact").dev ** 2)
        nonov.append(A.adev(x, 1.0, ms, "phase").dev ** 2)
    exact, fast, nonov = map(np.array, (exact, fast, nonov))
    assert np.all(acc.result().stride == ms // 8)

    def emp_edf(v: np.ndarray) -> np.ndarray:
        return 2.0 * v.mean(0) ** 2 / v.var(0, ddof=1)

    e_exact, e_fast, e_nonov = emp_edf(exact), emp_edf(fast), emp_edf(nonov)
    alpha = 0 if noise == "white_fm" else -2
    e_theory = np.array([E.edf("oadev", alpha, int(m), n + 1) for m in ms])
    # the EDF reported for the strided estimate (Greenhall with S = m/s): for FM within 2 %
    # of the overlapping one, and as close to the scatter
    e_reported = np.array([E.edf("oadev", alpha, int(m), n + 1, int(m) // 8) for m in ms])
    assert np.all(np.abs(e_reported / e_theory - 1) < 0.02), (e_reported, e_theory)
    assert np.all(np.abs(e_fast / e_reported - 1) < 0.25), (e_fast, e_reported)
    np.testing.assert_allclose(fast.mean(0), exact.mean(0), rtol=0.03)  # unbiased
    assert np.all(e_fast >= 0.9 * e_exact), (e_fast, e_exact)
    assert np.all(np.abs(e_fast / e_theory - 1) < 0.25), (e_fast, e_theory)
    if noise == "white_fm":  # here overlapping matters: the check can tell strides apart
        assert np.all(e_nonov < 0.8 * e_exact)


def test_other_deviations_on_white_fm() -> None:
    """All estimators agree with the white-FM expectation N / sqrt(tau) (mdev: /sqrt(2))."""
    y = _white(400_000, 7, 0.5)
    for kind, factor in (("oadev", 1.0), ("adev", 1.0), ("ohdev", 1.0), ("hdev", 1.0),
                         ("totdev", 1.0), ("mdev", np.sqrt(0.5))):
        ms = [16, 64] if kind == "mdev" else [1, 4, 16]  # MVAR/AVAR -> 1/2 for large m
        r = A.DEVIATIONS[kind](y, 0.01, ms, data_type="rate")
        expected = 0.5 * np.sqrt(0.01) / np.sqrt(r.tau_s) * factor
        np.testing.assert_allclose(r.dev, expected, rtol=0.05, err_msg=kind)


def test_invalid_inputs() -> None:
    with pytest.raises(ValueError):
        A.oadev(np.zeros(1), 1.0)
    with pytest.raises(ValueError):
        A.oadev(np.zeros(100), 1.0, mode="approximate")
    with pytest.raises(ValueError):
        A.OadevAccumulator(1.0, [], "fast")


def test_gram_pyramid_equals_direct_sums() -> None:
    """The polyphase-Gram pyramid (fast mode) gives the fully overlapping sums for m <= 15
    and the stride-2^j sums for m = k 2^j, on random-walk FM with a large offset, for any
    chunking (the chunk boundaries cut rows, blocks and pairs)."""
    from rigctl.solvers import allan_stream as S

    rng = np.random.default_rng(21)
    n = 150_001
    y = 9.80665 + 1e-3 * rng.standard_normal(n) + 1e-6 * np.cumsum(rng.standard_normal(n))
    ms = np.array([1, 2, 3, 5, 7, 8, 11, 15, 16, 18, 26, 30, 48, 60, 104, 240, 1792, 3840])
    assert all(S.conforming(int(m)) is not None for m in ms)
    assert S.conforming(17) is None and S.conforming(40) == (2, 10)
    x = A.phase_from_rate(y, 1.0)
    ref_sum, ref_cnt = [], []
    for m in ms:
        s = m // S.conforming(int(m))[1]  # stride 2^j
        xs, k = x[::s], m // s
        d = xs[2 * k:] - 2 * xs[k: xs.size - k] + xs[: xs.size - 2 * k]
        ref_sum.append(np.sum(d * d))
        ref_cnt.append(d.size)
    for chunks in ([n], [5, 16_000, 1, 33, 70_000, n - 86_039], [4096] * 36 + [n - 4096 * 36]):
        pyr = S.GramPyramid(ms)
        a = 0
        for c in chunks:
            pyr.feed(y[a: a + c], offset=9.80665)
            a += c
        assert a == n
        tot, cnt, stride = pyr.sums()
        np.testing.assert_allclose(tot, ref_sum, rtol=1e-11)
        assert cnt.tolist() == ref_cnt
        assert stride.tolist() == [1] * 8 + [int(m) // S.conforming(int(m))[1] for m in ms[8:]]


def test_exact_mode_gram_path_equals_direct() -> None:
    """Exact mode on a long series (> 2^20 points) uses the Gram for m <= 16 and blocked
    direct sums with 2x precomputed above: same sums as the textbook ones."""
    n = 1_100_000
    y = _white(n, 22) + 0.5 + np.cumsum(_white(n, 23, 1e-3))
    ms = np.array([1, 2, 3, 9, 16, 17, 100, 140_001, 270_000])
    got = A.oadev(y, 0.5, ms, "rate", mode="exact")
    x = A.phase_from_rate(y, 0.5)
    for m, d, nt in zip(ms, got.dev, got.n_terms):
        dd = x[2 * m:] - 2 * x[m: x.size - m] + x[: x.size - 2 * m]
        assert d == pytest.approx(np.sqrt(np.mean(dd * dd) / 2) / (m * 0.5), rel=1e-12)
        assert nt == dd.size


def test_blas_single_thread_restores() -> None:
    from rigctl.solvers import allan_stream as S

    fns = S._openblas_local()
    if not fns:
        pytest.skip("numpy/scipy do not bundle OpenBLAS here")
    before = [fn(1) for fn in fns]
    for fn, b in zip(fns, before):
        fn(b)
    with S.blas_single_thread():
        inside = [fn(1) for fn in fns]
    after = [fn(1) for fn in fns]
    for fn, b in zip(fns, before):
        fn(b)
    assert inside == [1] * len(fns) and after == before
