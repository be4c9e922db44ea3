"""The emulator's compiled paths (sim/fused.py, block_iir.run_direct) against the plain numpy
ones they replace: the same model, to rounding."""
from __future__ import annotations

import numpy as np
import pytest

from rigctl.sim import block_iir as bi
from rigctl.sim import error_model as EM
from rigctl.sim import fused as FU
from rigctl.sim import spectral_factor as sf
from rigctl.sim.profiles import get_profile

pytestmark = pytest.mark.skipif(not FU.HAVE_NUMBA, reason="numba (the 'fast' extra) not installed")


def _run(name: str, chunks: list[int], compiled: bool, monkeypatch) -> np.ndarray:
    monkeypatch.setattr(EM._fused, "HAVE_NUMBA", compiled)
    m = EM.ImuErrorModel.from_profile(get_profile(name), seed=3)
    out = []
    for n in chunks:
        g = m.sample_grid(n)
        k = len(g.t_internal)
        w = np.zeros((k, 3))
        w[:, 2] = np.sin(0.5 * g.t_eval)
        w[:, 0] = 0.3 * np.cos(0.2 * g.t_eval)
        f = np.tile([0.1, 0.0, 9.80665], (k, 1)) + 0.1 * w
        out.append(np.hstack(m.apply(g.t_internal, f, w)[:2]))
    return np.vstack(out)


@pytest.mark.parametrize("name", ["consumer_mems", "mti_class", "tactical"])
def test_fused_equals_numpy_path_and_chunking(name: str, monkeypatch) -> None:
    fused = _run(name, [1500], True, monkeypatch)
    pieces = _run(name, [301, 700, 499], True, monkeypatch)
    plain = _run(name, [1500], False, monkeypatch)
    assert np.array_equal(fused, pieces)
    # outputs are LSB-quantized: a last-bit difference can move a value by one LSB at most
    lsb = np.max(np.abs(np.diff(np.unique(plain))))
    assert np.max(np.abs(fused - plain)) <= max(1e-12 * np.max(np.abs(plain)), lsb)


def test_sincos_of_cycle_fraction() -> None:
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(0, 1e5, 20_000))
    for f in (0.37, 47.3, 113.0):
        s, c = np.empty(t.size), np.empty(t.size)
        FU._sincos_cycles(f, t, s, c)
        u = f * t
        u -= np.floor(u)
        # independent reference in extended precision on the same cycle fraction
        ul = u.astype(np.longdouble) * (2 * np.pi)
        assert np.max(np.abs(s - np.sin(ul).astype(float))) < 1e-15
        assert np.max(np.abs(c - np.cos(ul).astype(float))) < 1e-15


def test_direct_cascade_equals_block_form() -> None:
    a = np.array([1e-7, 3e-5, 2e-3, 0.05, 0.9, 4.0, 5.0])
    b_axes = [a * 1.7, np.r_[a[:-1] * 2.5, np.inf], np.full(6, np.inf)]
    c_int = np.array([[0.0, 1.0], [1 - np.exp(-2e-6), 1.0], [0.3, 0.0]])
    gain = np.array([1.3, 0.02, 7.0])
    res = np.array([sf.residues(a, b) for b in b_axes])
    blk, direct = bi.BlockCascade(a, res, c_int, gain, 64), bi.BlockCascade(a, res, c_int, gain, 64)
    rng = np.random.default_rng(3)
    s0 = rng.standard_normal((3, len(a))) * 50.0
    blk.state[:, : len(a)] = s0
    direct.state[:, : len(a)] = s0
    eps = rng.standard_normal((3, 3072))
    ref = np.concatenate([blk.run(eps[:, i:i + 1024]).copy() for i in range(0, 3072, 1024)], axis=1)
    cuts = [0, 5, 1000, 2048, 3072]
    got = np.concatenate([bi.run_direct(direct, np.ascontiguousarray(eps[:, a0:a1]), np.empty((3, a1 - a0)))
                          for a0, a1 in zip(cuts[:-1], cuts[1:])], axis=1)
    assert np.max(np.abs(got - ref)) <= 1e-11 * np.max(np.abs(ref))
