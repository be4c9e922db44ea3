"""rigctl.sim.iir against scipy.signal: the same numbers, bit for bit, and the emulator's import
without scipy.signal and scipy.optimize (~0.6 s of CPU in every emulated run, sim up and resume)."""
from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from scipy import signal

from rigctl.sim import iir
from rigctl.sim.effects import ClockModel
from rigctl.sim.table import ServoParams, TableAxis

from helpers import ROOT


def _bits(x: np.ndarray) -> bytes:
    """The float64 bit patterns (so -0.0 != 0.0 and NaN payloads count)."""
    return np.ascontiguousarray(x, dtype=np.float64).tobytes()


@pytest.mark.parametrize("seed", range(6))
def test_lfilter_is_scipys_bit_for_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for trial in range(60):
        n_a = int(rng.integers(2, 6))
        a = np.r_[1.0 if trial % 3 else rng.uniform(0.5, 3.0), 0.3 * rng.standard_normal(n_a - 1)]
        b = rng.standard_normal(int(rng.integers(1, 7)))
        x = rng.standard_normal(int(rng.integers(1, 400))) * 10.0 ** rng.integers(-9, 4)
        zi = rng.standard_normal(max(a.size, b.size) - 1)
        y_ref, zf_ref = signal.lfilter(b, a, x, zi=zi)
        y, zf = iir.lfilter(b, a, x, zi)
        assert _bits(y) == _bits(y_ref) and _bits(zf) == _bits(zf_ref), (trial, b, a)
        # in chunks, carrying the state: the same samples
        cut = int(rng.integers(1, x.size + 1))
        y1, z1 = iir.lfilter(b, a, x[:cut], zi)
        y2, z2 = iir.lfilter(b, a, x[cut:], z1)
        assert _bits(np.r_[y1, y2]) == _bits(y_ref) and _bits(z2) == _bits(zf_ref)


@pytest.mark.parametrize("seed", range(3))
def test_lfilter_prepared_is_scipys_bit_for_bit(seed: int) -> None:
    """The turntable's per-poll path (coefficients normalised once by iir.prepare, any x: a
    strided or read-only one is copied) gives scipy's numbers and state, block after block."""
    rng = np.random.default_rng(100 + seed)
    for trial in range(40):
        n_a = int(rng.integers(2, 5))
        a = np.r_[1.0 if trial % 2 else rng.uniform(0.5, 3.0), 0.3 * rng.standard_normal(n_a - 1)]
        b = rng.standard_normal(int(rng.integers(1, 6)))
        x = rng.standard_normal(2 * int(rng.integers(1, 200)))
        zi = rng.standard_normal(max(a.size, b.size) - 1)
        y_ref, zf_ref = signal.lfilter(b, a, x, zi=zi)
        bp, ap = iir.prepare(b, a)
        y, zf = iir.lfilter_prepared(bp, ap, x, zi)
        assert _bits(y) == _bits(y_ref) and _bits(zf) == _bits(zf_ref), (trial, b, a)
        assert zf is not zi
        # strided and read-only signals, in blocks carrying the state
        xs = np.repeat(x, 2)[::2]
        xs.flags.writeable = False
        cut = int(rng.integers(0, x.size + 1))
        y1, z1 = iir.lfilter_prepared(bp, ap, xs[:cut], zi)
        y2, z2 = iir.lfilter_prepared(bp, ap, xs[cut:], z1)
        assert _bits(np.r_[y1, y2]) == _bits(y_ref) and _bits(z2) == _bits(zf_ref)


def test_lfilter_zero_input_keeps_the_sign_of_zero_as_scipy() -> None:
    """The clock wander's b = [1] is padded with a zero (x b[1] = +-0): scipy's operations."""
    for zi in (np.array([0.0]), np.array([-0.0]), np.array([1e-300])):
        x = np.array([0.0, -0.0, 0.0, 5e-324])
        y_ref, zf_ref = signal.lfilter([1.0], [1.0, -0.5], x, zi=zi)
        y, zf = iir.lfilter([1.0], [1.0, -0.5], x, zi)
        assert _bits(y) == _bits(y_ref) and _bits(zf) == _bits(zf_ref)


def test_lfilter_of_no_samples_keeps_the_state() -> None:
    """The one difference from scipy 1.17: on an empty signal its zf is uninitialised memory
    (e.g. [-1.8e-108, 3.3e+215] for zi [1, 2]); here it is zi. The emulator never filters an
    empty block (sim.world advances the table only over new grid points)."""
    zi = np.array([1.0, 2.0])
    y, zf = iir.lfilter([0.1, 0.2, 0.3], [1.0, -0.5, 0.1], np.zeros(0), zi)
    assert y.shape == (0,) and _bits(zf) == _bits(zi) and zf is not zi


def test_lfilter_rejects_what_it_does_not_do() -> None:
    with pytest.raises(ValueError):
        iir.lfilter([1.0], [1.0], np.zeros(3), np.zeros(0))  # FIR: not the recurrence's case
    with pytest.raises(ValueError):
        iir.lfilter([1.0], [1.0, 0.5], np.zeros((2, 3)), np.zeros(1))


def test_cont2discrete_zoh_is_scipys_bit_for_bit() -> None:
    """The servo error filters of a table axis (natural 0.5-50 Hz, damping 0.05-2, grid steps of
    0.5-10 ms) and a third-order case with den[0] != 1, against scipy.signal.cont2discrete."""
    cases = []
    for f_n, zeta, dt in ((0.5, 0.05, 1e-3), (4.0, 0.6, 1e-3), (5.0, 0.6, 1 / 2000), (6.0, 1.0, 0.0025),
                          (13.7, 2.0, 0.01), (50.0, 0.6, 1e-3)):
        wn = 2 * math.pi * f_n
        cases.append(([1.0, 2 * zeta * wn, wn * wn], dt))
    cases.append(([2.0, 3.0, 5.0, 7.0], 0.1))
    for den, dt in cases:
        for num in ([-1.0], [-1.0, 0.0], [0.5, -2.0, 1.0][: len(den)]):
            b_ref, a_ref, _ = signal.cont2discrete((num, den), dt, method="zoh")
            b, a = iir.cont2discrete_zoh(num, den, dt)
            assert b.shape == b_ref.shape and a.shape == a_ref.shape
            assert _bits(b) == _bits(b_ref) and _bits(a) == _bits(a_ref), (num, den, dt)


def test_table_axis_and_clock_wander_equal_the_scipy_recurrences() -> None:
    """The emulator's two users, end to end: a table axis moving through a jerk-free trapezoid
    in blocks of uneven length, and the IMU clock's wander, against scipy.signal run here."""
    dt = 1e-3
    servo = ServoParams(natural_hz=5.0, damping=0.6)
    ax = TableAxis(servo, vmax=math.radians(300), amax=math.radians(200), continuous=True, dt=dt)
    ax.command(0.0, 1, math.radians(90))
    wn = 2 * math.pi * 5.0
    den = [1.0, 2 * 0.6 * wn, wn * wn]
    b_e, a_e, _ = signal.cont2discrete(([-1.0], den), dt, method="zoh")
    b_de, a_de, _ = signal.cont2discrete(([-1.0, 0.0], den), dt, method="zoh")
    t = dt * np.arange(1, 2501)
    _, _, acc = ax.profile.evaluate(t)
    e_ref = signal.lfilter(np.ravel(b_e), a_e, acc)
    de_ref = signal.lfilter(np.ravel(b_de), a_de, acc)
    p, v, _ = ax.profile.evaluate(t)
    x, w = [], []
    for lo, hi in ((0, 1), (1, 700), (700, 701), (701, 2500)):
        xb, wb, _ = ax.advance(t[lo:hi])
        x.append(xb)
        w.append(wb)
    assert _bits(np.concatenate(x)) == _bits(p + e_ref)
    assert _bits(np.concatenate(w)) == _bits(v + de_ref)
    assert np.max(np.abs(e_ref)) > 1e-4  # the servo lag is really exercised (rad)

    clk = ClockModel(100.0, drift_ppm=50.0, wander_ppm=2.0, wander_tau_s=30.0, seed=7)
    ref = ClockModel(100.0, drift_ppm=50.0, wander_ppm=2.0, wander_tau_s=30.0, seed=7)
    g = ref._g
    for n in (1, 250, 3, 4000):
        _, _, e = clk.next(n)
        w_ = ref._rng_w.standard_normal(n) * (ref.wander_ppm * np.sqrt(1 - ref._phi**2))
        g_ref, _ = signal.lfilter([1.0], [1.0, -ref._phi], w_, zi=ref._phi * g)
        g = g_ref[-1:].copy()
        assert _bits(e) == _bits(ref.drift_ppm + g_ref)


def test_the_emulator_imports_without_scipy_signal_or_optimize() -> None:
    """What every emulated `rigctl run` / `sim up` / resume imports before its clock starts
    (rigctl.engine.rig.open_rig): the emulator, without scipy.signal (~0.5 s of CPU; its rarer
    filters import it when a configuration asks for them) and without scipy.optimize (~0.17 s;
    the tap solver imports it when it fits)."""
    code = ("import sys, rigctl.cli, rigctl.run.runner, rigctl.engine.rig\n"
            "from rigctl.sim.world import SimWorld\n"
            "print(sorted(m for m in sys.modules if m.startswith(('scipy.signal', 'scipy.optimize'))))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "[]", r.stdout
