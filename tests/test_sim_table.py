"""Turntable servo realism (sim/table.py): encoder noise, rate ripple and wobble, each showing
its signature at the configured magnitude; the defaults leave the table as it was."""
import json
import math

import numpy as np
import pytest

from rigctl.clock import make_clock
from rigctl.config.config import load_config
from rigctl.devices import AxisStatus
from rigctl.sim.table import POSITION, RATE, ServoParams, SimTurntable
from rigctl.sim.world import SimTableDevice, SimWorld

from helpers import derived_config

DT = 1e-3
VMAX, AMAX = np.radians([300.0, 300.0, 500.0]), np.radians([200.0, 200.0, 400.0])


def _table(seed: int = 3, **servo) -> SimTurntable:
    return SimTurntable([ServoParams(natural_hz=5.0, **servo) for _ in range(3)], VMAX, AMAX,
                        [True] * 3, DT, np.random.default_rng(seed))


def _run(table: SimTurntable, t0: float, t1: float) -> tuple[np.ndarray, ...]:
    t = np.arange(round(t0 / DT) + 1, round(t1 / DT) + 1) * DT
    return (t, *table.advance(t))


def test_encoder_noise_has_the_configured_sigma():
    sigma = math.radians(1e-3)
    table = _table(encoder_noise=sigma, encoder_lsb=math.radians(1e-6))
    table.command(0.0, [POSITION] * 3, np.radians([10.0, 20.0, 30.0]))
    _run(table, 0.0, 5.0)
    reads = np.array([table.measured(5.0)[0] for _ in range(4000)])
    assert np.all(np.abs(reads.mean(axis=0) - np.radians([10.0, 20.0, 30.0])) < 5 * sigma / 60)
    # 1-sigma of a sample std over 4000 reads is 1.1 %
    assert np.allclose(reads.std(axis=0, ddof=1) / sigma, 1.0, atol=0.05)
    quiet = _table()  # default: no noise, readings repeat exactly
    quiet.command(0.0, [POSITION] * 3, np.radians([10.0, 20.0, 30.0]))
    _run(quiet, 0.0, 5.0)
    assert len({tuple(quiet.measured(5.0)[0]) for _ in range(20)}) == 1


def test_rate_ripple_per_revolution_and_at_a_frequency():
    r_rev, r_f, f_r = 2e-4, 1e-4, 7.0
    table = _table(ripple_per_rev=r_rev, ripple_per_rev_phase=0.4, ripple_fraction=r_f,
                   ripple_hz=f_r, ripple_phase=1.1)
    rate = math.radians(100.0)
    for ax in table.axes:
        ax.command(0.0, RATE, rate)
    _run(table, 0.0, 3.0)  # accelerate (0.5 s) and settle
    t, ang, w, _ = _run(table, 3.0, 10.2)  # two whole revolutions of the axis
    y = w[:, 0] / rate - 1.0
    p = ang[:, 0]
    a = np.column_stack([np.sin(p), np.cos(p), np.sin(2 * np.pi * f_r * t), np.cos(2 * np.pi * f_r * t),
                         np.ones_like(t)])
    c, *_ = np.linalg.lstsq(a, y, rcond=None)
    assert math.hypot(c[0], c[1]) == pytest.approx(r_rev, rel=0.01)
    assert math.atan2(c[1], c[0]) == pytest.approx(0.4, abs=0.01)
    assert math.hypot(c[2], c[3]) == pytest.approx(r_f, rel=0.01)
    # the angle is the integral of the rate (ripple included)
    assert np.allclose(np.diff(ang[:, 0]), 0.5 * (w[1:, 0] + w[:-1, 0]) * DT, atol=1e-8)


def test_ripple_residual_is_removed_at_rest():
    table = _table(ripple_per_rev=5e-4, ripple_fraction=3e-4, ripple_hz=3.0)
    target = math.radians(137.0)
    table.command(0.0, [POSITION] * 3, np.full(3, target))
    _, ang, _, _ = _run(table, 0.0, 6.0)
    s = table.axes[0].servo
    assert abs(ang[-1, 0] - target) < s.in_position_window / 10
    assert table.axes[0].status(6.0) & AxisStatus.TARGET_REACHED


def _world(tmp_path, wobble: float, harmonic: int = 2):
    tmp_path.mkdir()
    cfg = load_config(derived_config(tmp_path, **{"table__sim__wobble_rad": [wobble, 0.0, 0.0],
                                                  "table__sim__wobble_harmonic": harmonic}))
    clock = make_clock("virtual", 1.0)
    world = SimWorld(cfg, clock)
    SimTableDevice(world).set_rate(np.array([math.radians(60.0), np.nan, np.nan]))
    clock.sleep(10.0)
    return world, world.take_imu()


def test_wobble_tilts_the_imu_attitude(tmp_path):
    """Outer-axis wobble A at harmonic n turning at W: same seed with and without, the
    accelerometers see gravity tilted by A (|df_xy| = g A) and the gyros the tilt rate n A W."""
    amp, n = 2e-4, 2
    w0, quiet = _world(tmp_path / "a", 0.0)
    w1, wob = _world(tmp_path / "b", amp, n)
    keep = quiet.time > 3.0  # at rate
    df = wob.specific_force[keep] - quiet.specific_force[keep]
    dw = wob.angular_rate[keep] - quiet.angular_rate[keep]
    g = w0.cfg.gravity
    assert np.allclose(np.hypot(df[:, 0], df[:, 1]), g * amp, rtol=0.01)
    assert np.allclose(np.hypot(dw[:, 0], dw[:, 1]), n * amp * math.radians(60.0), rtol=0.01)
    # the pattern turns with the axis: both signs of the body-x component appear
    assert df[:, 0].max() > 0.9 * g * amp and df[:, 0].min() < -0.9 * g * amp
    truth = w1.truth()["table"]["axes"][0]
    assert truth["wobble_rad"] == amp and truth["wobble_harmonic"] == n
    json.dumps(w1.truth())


def test_default_table_truth_is_recorded(tmp_path):
    cfg = load_config(derived_config(tmp_path))
    world = SimWorld(cfg, make_clock("virtual", 1.0))
    axes = world.truth()["table"]["axes"]
    assert [a["natural_hz"] for a in axes] == [4.0, 5.0, 6.0]
    assert all(a["encoder_noise_rad"] == 0 and a["wobble_rad"] == 0 and a["rate_ripple_fraction"] == 0
               for a in axes)
    assert axes[0]["rate_limit_rad_s"] == pytest.approx(math.radians(300.0))


@pytest.mark.parametrize("moves", [
    [(0.0, POSITION, 90.0)],  # trapezoid
    [(0.0, POSITION, 4.0)],  # triangle (coast inserted at the peak)
    [(0.0, RATE, 100.0), (2.0, RATE, -100.0), (4.0, POSITION, 30.0)],  # reversal, stop and go
])
def test_jerk_limit(moves):
    jmax = math.radians(2000.0)
    table = _table(jerk_max=jmax)
    free = _table()
    t_end, segs = 8.0, []
    bounds = [m[0] for m in moves[1:]] + [t_end]
    t_prev = 0.0
    for (t0, mode, value), t1 in zip(moves, bounds):
        for tb in (table, free):
            tb.axes[0].command(t0, mode, math.radians(value))
        ax = table.axes[0]
        tt = np.arange(round(t_prev / DT) + 1, round(t1 / DT) + 1) * DT
        segs.append((tt, ax.profile.smoothed(tt, ax.t_jerk)))
        table.advance(tt)
        free.advance(tt)
        t_prev = t1
    t = np.concatenate([s[0] for s in segs])
    p, v, a = (np.concatenate([s[1][i] for s in segs]) for i in range(3))
    assert table.axes[0].t_jerk == pytest.approx(AMAX[0] / jmax)
    assert np.max(np.abs(np.diff(a))) / DT <= jmax * (1 + 1e-6)  # the profile's jerk
    assert np.max(np.abs(a)) <= AMAX[0] * (1 + 1e-9)
    assert np.max(np.abs(v)) <= VMAX[0] * (1 + 1e-9)
    # continuous and consistent: the rate is the derivative of the position (trapezoid rule on
    # a rate with |v''| <= jmax: error <= jmax DT^2 / 12)
    assert np.allclose(np.diff(p) / DT, 0.5 * (v[1:] + v[:-1]), rtol=0, atol=jmax * DT**2 / 12 * 1.001 + 1e-9)
    # the same final target as without the jerk limit, and the controller gets there
    target = math.radians(moves[-1][2])
    assert p[-1] == pytest.approx(target, abs=1e-9)
    assert table.axes[0].last[0] == pytest.approx(free.axes[0].last[0], abs=1e-6)
    assert table.axes[0].status(t_end) & AxisStatus.TARGET_REACHED
    # without the limit the acceleration steps (one-sample jumps of amax)
    fa = free.axes[0].profile.evaluate(t)[2]
    assert np.max(np.abs(np.diff(fa))) >= 0.99 * AMAX[0]


def test_servo_options_from_the_config(tmp_path):
    cfg = load_config(derived_config(tmp_path, **{
        "table__sim__jerk_dps3": [1000, 2000, 4000], "table__sim__encoder_noise_deg": 1e-4,
        "table__sim__rate_ripple_per_rev": [1e-4, 0, 0], "table__sim__rate_ripple_hz": 5.0}))
    world = SimWorld(cfg, make_clock("virtual", 1.0))
    axes = world.truth()["table"]["axes"]
    assert [a["jerk_limit_rad_s3"] for a in axes] == pytest.approx(np.radians([1000, 2000, 4000]))
    assert [a["encoder_noise_rad"] for a in axes] == pytest.approx([math.radians(1e-4)] * 3)
    assert [a["rate_ripple_per_rev_fraction"] for a in axes] == [1e-4, 0, 0]
    assert world.table.axes[2].t_jerk == pytest.approx(math.radians(400) / math.radians(4000))


def test_profile_values_do_not_depend_on_the_other_times_asked():
    """Profile.evaluate takes a shortcut when every time asked lies in the last piece (an axis
    at rest after its move, most polls): a time gives the same bits whether asked alone (the
    shortcut), with times inside the move (the piecewise path) or before the profile's start."""
    from rigctl.sim.table import Profile

    rate = Profile.to_rate(1.0, 0.3, -0.4, 0.7, 1.3)  # its last piece moves at 0.7 rad/s
    rate.prev = Profile.to_rate(0.0, 0.0, 0.2, 0.0, 1.0)
    position = Profile.to_position(1.0, 0.3, 0.0, 2.1, 0.8, 1.7)
    position.prev = rate.prev
    for prof in (position, rate):
        _same_bits_alone_and_together(prof)


def _same_bits_alone_and_together(prof) -> None:
    assert len(prof.t) >= 2
    t_all = np.r_[np.linspace(-0.5, prof.end + 1.0, 257), prof.end, prof.end + 1e-9]
    together = prof.evaluate(t_all)
    for i, ti in enumerate(t_all):
        alone = prof.evaluate(np.array([ti]))
        for k in range(3):
            assert together[k][i].tobytes() == alone[k][0].tobytes(), (ti, k)
    late = t_all[t_all >= prof.t[-1]]
    assert late.size > 40  # the shortcut taken with many times too
    for k, got in enumerate(prof.evaluate(late)):
        assert got.tobytes() == np.array([together[k][list(t_all).index(x)] for x in late]).tobytes()


def test_one_sample_read_is_the_array_path_bit_for_bit():
    """TableAxis.at_one (the encoder read at every poll) gives the bits of at(np.array([t])) --
    servos under-, over- and critically damped, jerk-limited, with ripple, after commands in
    every mode, with history forgotten, inside and before the kept history (both raise)."""
    from rigctl.sim.table import OFF, TableAxis

    rng = np.random.default_rng(7)
    n_fast = n_cmp = 0
    for _ in range(60):
        sp = ServoParams(natural_hz=rng.uniform(2, 8), damping=float(rng.choice([0.6, 1.0, 1.3])),
                         jerk_max=float(rng.choice([math.inf, math.inf, 50.0])),
                         ripple_per_rev=float(rng.choice([0.0, 0.0, 1e-3])))
        dt = float(rng.choice([0.001, 0.005]))
        ax = TableAxis(sp, 5.0, 3.0, bool(rng.integers(2)), dt)
        now = 0.0
        for _ in range(4):
            ax.command(now + rng.uniform(0, 0.3), int(rng.choice([POSITION, RATE, OFF])), float(rng.uniform(-3, 3)))
            grid = now + dt * np.arange(1, int(rng.integers(1, 300)) + 1)
            ax.advance(grid)
            now = float(grid[-1])
            if rng.random() < 0.3:
                ax.forget_before(now - rng.uniform(0, 0.2))
            for t in now + rng.uniform(-0.4, dt, 10):
                try:
                    x, w, _ = ax.at(np.array([t]))
                    want = np.array([x[0], w[0]])
                except RuntimeError:
                    with pytest.raises(RuntimeError):
                        ax.at_one(t)
                    continue
                got = np.array(ax.at_one(t))
                assert got.tobytes() == want.tobytes(), (t, got, want)
                n_cmp += 1
                n_fast += sp.jerk_max == math.inf and not sp.ripple_per_rev
    assert n_cmp > 1000 and n_fast > 500  # both paths exercised


def test_profile_at_rest_is_the_general_arithmetic_bit_for_bit():
    """Profile.evaluate's at-rest shortcut (last piece, zero rate and acceleration) gives the
    floats of p + v dt + a dt^2 / 2, v + a dt, a -- signed zeros included -- for dt >= 0."""
    import itertools

    from rigctl.sim.table import Profile

    t0 = 2.5
    t = t0 + np.array([0.0, 1e-12, 0.5, 3.0, 1e5])
    for p0, v0, a0 in itertools.product([0.0, -0.0, 1.5, -2.25, 1e-300, -1e-300, 3e10], [0.0, -0.0], [0.0, -0.0]):
        prof = Profile(t0, p0, v0)
        prof.a[-1] = a0
        dt = t - t0
        want = (p0 + v0 * dt + 0.5 * a0 * dt * dt, v0 + a0 * dt, np.full(t.shape, a0))
        for got, w in zip(prof.evaluate(t), want):
            assert got.tobytes() == w.tobytes(), (p0, v0, a0, got, w)


def test_quiet_history_shortcut_is_the_general_path_bit_for_bit():
    """TableAxis.at on a history whose servo error has underflowed to zero (an axis at rest for
    long) skips the propagation; its values are those of the general path (the same call with
    the shortcut disabled), byte for byte, and axes that rest long enough do take it."""
    from rigctl.sim.table import OFF, TableAxis

    rng = np.random.default_rng(11)
    quiet = 0
    for _ in range(12):
        sp = ServoParams(natural_hz=float(rng.uniform(6, 10)), damping=float(rng.choice([0.6, 1.0, 1.3])))
        dt = 0.01
        ax = TableAxis(sp, 5.0, 3.0, bool(rng.integers(2)), dt)
        now = 0.0
        for _ in range(6):
            if rng.random() < 0.5:
                ax.command(now + rng.uniform(0, 0.3), int(rng.choice([POSITION, RATE, OFF])), float(rng.uniform(-2, 2)))
            grid = now + dt * np.arange(1, int(rng.choice([5, 50, 6000])) + 1)
            ax.advance(grid)
            now = float(grid[-1])
            ax.forget_before(now - rng.uniform(0.3, 0.5))  # the reads below stay inside the kept history
            for _ in range(10):
                t = now + rng.uniform(-0.3, dt, int(rng.choice([1, 5, 50])))
                if not ax._hist_quiet:
                    continue
                quiet += 1
                got = ax.at(t)
                ax._hist_quiet = False
                want = ax.at(t)
                ax._hist_quiet = True
                assert all(g.tobytes() == w.tobytes() for g, w in zip(got, want)), t
    assert quiet > 50
