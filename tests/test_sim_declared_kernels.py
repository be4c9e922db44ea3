"""The declared IMU model's compiled block arithmetic (sim/declared_kernels.py) against the numpy
code it stands in for: the same floats, bit for bit, on many block lengths and on special values
(signed zeros, quarter turns, tiny angles), and a whole emulated run the same sample for sample
with the kernels on and off. A kernel with another rounding (another association of the
rotation product, or of the model's sum) is caught by the same comparison."""
from __future__ import annotations

import numpy as np
import pytest

from rigctl.config.config import load_config
from rigctl.frames import _rot, gimbal_rate_body
from rigctl.sim import declared_kernels as K
from rigctl.sim.imu import DeclaredImuModel
from rigctl.sim.table import POSITION, RATE
from rigctl.sim.world import SimWorld

from helpers import ROOT

pytestmark = pytest.mark.skipif(not K.HAVE_NUMBA, reason="the kernels need numba (the fast extra)")

LENGTHS = (2, 3, 4, 5, 6, 7, 8, 9, 16, 17, 50, 64, 200, 1000, 4099)


def _need_exact():
    if not K.exact(DeclaredImuModel):
        pytest.skip("numpy/BLAS here fuse other operations than the kernels: the numpy code runs")


def test_kernels_are_numpy_bit_for_bit():
    _need_exact()
    model = K.probe_model(DeclaredImuModel)
    for seed in range(4):
        assert K.compare(model, lengths=LENGTHS, seed=seed)
    # the model of configs/sim.yaml (thermal terms without hysteresis or rate terms) and one
    # without thermal errors
    world = SimWorld(load_config(ROOT / "configs" / "sim.yaml"), _Clock())
    assert K.compare(world.imu_model, lengths=LENGTHS, seed=7)
    world.imu_model.thermal = None
    assert K.compare(world.imu_model, lengths=LENGTHS, seed=8)


def _wrong_body(ang, rates, g, w_site):
    """body_references with the rotation product associated the other way, R_z (R_y R_x)."""
    c_bn = _rot("z", ang[:, 0]) @ (_rot("y", ang[:, 1]) @ _rot("x", ang[:, 2]))
    c_nb = np.swapaxes(c_bn, -1, -2)
    return c_nb @ np.array([0.0, 0.0, g]), c_nb @ w_site + gimbal_rate_body(ang, rates)


def _wrong_table_refs(ang, rates, lat, g, **geometry):
    """The profile model's table references with C^T made contiguous before C^T Omega: BLAS' gemv
    (fused multiply-adds) instead of numpy's own loop over the transposed view."""
    from rigctl.frames import earth_rate_enu
    from rigctl.sim.effects import table_attitude_and_rate

    C, w_tab = table_attitude_and_rate(ang, rates, **geometry)
    CT = np.ascontiguousarray(np.swapaxes(C, 1, 2))
    return CT @ np.array([0.0, 0.0, g]), CT @ earth_rate_enu(lat) + w_tab


def _wrong_deterministic(model, f_true, w_true, T, H, R):
    """deterministic_numpy with the bias added last: (M f + k2 f^2) + b."""
    f, w = model.deterministic_numpy(f_true, w_true, T, H, R)
    f0 = model.accel_bias + model.turn_on_accel + f_true @ model.accel_matrix.T + model.accel_quadratic * f_true**2
    f1 = (f_true @ model.accel_matrix.T + model.accel_quadratic * f_true**2) + (model.accel_bias + model.turn_on_accel)
    return f - f0 + f1, w


def test_a_kernel_with_other_rounding_is_caught():
    """The comparison exact() runs tells a kernel of another summation order from numpy's: with
    the rotation product or the model's sum associated differently it reports a difference."""
    _need_exact()
    model = K.probe_model(DeclaredImuModel)
    assert K.compare(model)  # the real kernels pass ...
    assert not K.compare(model, body=_wrong_body)  # ... one rounding apart does not
    assert not K.compare(model, deterministic=_wrong_deterministic)
    assert not K.compare(model, table_refs=_wrong_table_refs)


class _Clock:
    t = 0.0

    def now(self) -> float:
        return self.t


def _run(cfg_path, kernels: bool, monkeypatch) -> list[bytes]:
    """The IMU blocks of a short emulated session (rest, a move, a rate, a power cycle) as bytes."""
    monkeypatch.setattr(K, "ready", K.exact if kernels else (lambda model_type: False))
    clock = _Clock()
    world = SimWorld(load_config(cfg_path), clock)
    out = []

    def poll(dt, n):
        for _ in range(n):
            clock.t += dt
            b = world.take_imu()
            out.append(b"".join(np.ascontiguousarray(getattr(b, f)).tobytes()
                                for f in ("time", "counter", "specific_force", "angular_rate", "temperature")))

    poll(0.5, 4)
    world.table.command(world.t, [POSITION] * 3, np.radians([90.0, 45.0, -30.0]))
    poll(0.05, 40)
    poll(0.01, 3)  # one-sample blocks: the numpy code either way
    for ax in world.table.axes:
        ax.command(world.t, RATE, np.radians(20.0))
    poll(0.2, 20)
    world.power_cycle_imu()
    poll(2.0, 5)
    return out


@pytest.mark.parametrize("cfg", ["sim.yaml", "sim-taps.yaml", "imu-declared-only"])
def test_emulated_run_same_with_and_without_kernels(cfg, monkeypatch, tmp_path):
    """A declared-model session (configs/sim.yaml: thermal terms, turn-on bias) gives the same
    bytes in every block with the compiled arithmetic as with numpy's; so do the profile models
    (sim-taps.yaml: mti_class at 1 kHz internal, its clock, taps; sim.yaml with the
    declared_only profile), whose table references and gimbal rates are compiled."""
    _need_exact()
    path = ROOT / "configs" / cfg
    if cfg == "imu-declared-only":
        import yaml
        c = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
        c["imu"]["sim"] = {"profile": "declared_only"}
        path = tmp_path / "declared_only.yaml"
        path.write_text(yaml.safe_dump(c))
    with_kernels = _run(path, True, monkeypatch)
    without = _run(path, False, monkeypatch)
    assert len(with_kernels) == len(without) > 60
    assert with_kernels == without
