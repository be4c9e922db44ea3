"""The emulated turntable's compiled block arithmetic (sim/table_kernels.py) against the numpy
code of TableAxis: scripted axes (every damping regime; moves, rates, stops, rests; blocks of
1-40 grid points; reads on, between and past the grid) give the same floats in every output and
state, and a kernel one rounding off is caught by the same comparison."""
from __future__ import annotations

import numpy as np
import pytest

from rigctl.sim import table_kernels as TK
from rigctl.sim.table import TableAxis

pytestmark = pytest.mark.skipif(not TK.HAVE_NUMBA, reason="the kernels need numba (the fast extra)")


def _need_exact():
    if not TK.exact(TableAxis):
        pytest.skip("libm or numpy here differ from the kernels' arithmetic: the numpy code runs")


def test_table_kernels_are_numpy_bit_for_bit():
    _need_exact()
    for seed in range(5):
        assert TK.compare(TableAxis, seed=seed, blocks=150)


def test_the_kernels_run_in_the_comparison(monkeypatch):
    """compare() runs the compiled advance and at (not the numpy code twice)."""
    _need_exact()
    calls = {"advance": 0, "at": 0}
    for name in calls:
        real = getattr(TK, name)

        def counted(*a, _real=real, _name=name):
            calls[_name] += 1
            return _real(*a)
        monkeypatch.setattr(TK, name, counted)
    assert TK.compare(TableAxis, seed=1)
    assert calls["advance"] > 20 and calls["at"] > 20


def test_a_kernel_one_rounding_off_is_caught(monkeypatch):
    _need_exact()
    real_at, real_advance = TK.at, TK.advance

    def at_off(axis, t):  # the angle's servo error added in the other order: p + (e + 0) -> (p + e) (1 + eps)
        x, w, acc = real_at(axis, t)
        return np.where(np.abs(x) > 0, x * (1 + 2.0**-52), x), w, acc

    monkeypatch.setattr(TK, "at", at_off)
    assert not TK.compare(TableAxis, seed=2)
    monkeypatch.setattr(TK, "at", real_at)

    def advance_off(axis, t):  # the rate one ulp off where it moves
        x, w, *rest = real_advance(axis, t)
        return (x, np.where(w != 0, np.nextafter(w, np.inf), w), *rest)

    monkeypatch.setattr(TK, "advance", advance_off)
    assert not TK.compare(TableAxis, seed=2)
