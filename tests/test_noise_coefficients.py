"""One type for IEEE 952 noise coefficients (rigctl.solvers.noise_coefficients) from the
emulator's config to the calibration's noise model.

* The PSDs in the module's docstring give its Allan variances: sigma^2(tau) =
  4 int S(f) sin^4(pi f tau) / (pi f tau)^2 df integrated here with numpy on a log grid, for
  N, B (1/f), K and a Gauss-Markov term (R's nominal PSD makes the integral diverge at f -> 0:
  a ramp is not stationary).
* JSON (what /results and /truth store) and config keys round-trip exactly.
* The chain: a coefficient set (three gyro axes with different N, the accelerometer's) written
  as an emulator config (``imu.sim.overrides``) -> ``rigctl run`` (the emulator reads it, /truth
  records it) -> ``rigctl allan`` (the fit's coefficients with intervals or bounds, stored in
  /results/allan) -> the noise model ``rigctl calibrate --noise allan`` uses. At every stage the
  same type, sensor and SI units; the fitted values against the config's: N within 5 % on every
  axis (the fit's 95 % interval is ~ +-1 %: a unit slip -- 60, sqrt(2), 2 pi, g -- or swapped axes,
  whose N differ by 20-50 %, would fail), and every K and B interval or bound holds the
  config's value.
"""
from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

from helpers import copy_recording
from rigctl.analysis.allan import load_noise
from rigctl.analysis.calibration import _noise
from rigctl.sim.profiles import ImuProfile
from rigctl.solvers.noise_coefficients import (SI_UNITS, Coefficient, GaussMarkov, NoiseCoefficients,
                                               from_json, to_config, to_json, triad)


def _avar_from_psd(m: NoiseCoefficients, tau: float) -> float:
    """IEEE 952's integral of the rate PSD, plain numpy (trapezoid in log f)."""
    lf = np.linspace(np.log(1e-9), np.log(1e5), 400_001)
    f = np.exp(lf)
    x = np.pi * f * tau
    y = m.psd(f) * np.sin(x) ** 4 / x**2 * f  # d f = f d(ln f)
    return float(4.0 * np.sum((y[1:] + y[:-1]) / 2.0 * np.diff(lf)))


@pytest.mark.parametrize("m", [NoiseCoefficients(N=2e-3), NoiseCoefficients(B=5e-4), NoiseCoefficients(K=3e-5),
                               NoiseCoefficients(gm=(GaussMarkov(1e-3, 30.0),)),
                               NoiseCoefficients(N=2e-3, K=3e-5, gm=(GaussMarkov(1e-3, 30.0),))])
def test_the_documented_psd_gives_the_allan_variance(m: NoiseCoefficients) -> None:
    for tau in (0.3, 3.0, 30.0, 300.0):
        assert _avar_from_psd(m, tau) == pytest.approx(float(m.avar(tau)), rel=2e-3), tau
    # and the equations of the table for each term alone, written out here
    tau = np.array([0.5, 5.0, 50.0])
    assert np.allclose(NoiseCoefficients(K=2.0).avar(tau), 4.0 * tau / 3.0)
    assert np.allclose(NoiseCoefficients(B=2.0).avar(tau), 4.0 * 2.0 * math.log(2.0) / math.pi)


def test_json_and_config_round_trip() -> None:
    m = NoiseCoefficients(Q=Coefficient(1e-6, upper95=4e-6, bound_from="curve"),
                          N=Coefficient(2e-4, (1.9e-4, 2.1e-4), (1.8e-4, 2.2e-4), edf=300.0),
                          B=Coefficient(3e-5, (2e-5, 4e-5), (1e-5, math.inf), edf=4.0), K=1e-6,
                          gm=(GaussMarkov(Coefficient(1e-4), 12.0),), flicker_tau_min_s=0.5,
                          flicker_tau_max_s=2e3, sensor="gyro", source="a test",
                          white_by_group={"orientation": 2e-4, "rate": 2.5e-4})
    back = from_json(json.loads(json.dumps(to_json(m))))
    assert back == m and back.B.ci95[1] == math.inf and not back.Q.resolved
    axes = triad("accel", N=[1e-3, 2e-3, 3e-3], K=4e-5, flicker_tau_max_s=500.0)
    section = to_config(axes, "accel")
    assert section["N_m_per_s2_per_sqrt_hz"] == [1e-3, 2e-3, 3e-3] and section["K_m_per_s3_per_sqrt_hz"] == 4e-5
    assert ImuProfile.read({"accel": {"noise": section}}).accel.noise.coefficients() == tuple(
        replace(a, source="emulator profile") for a in axes)
    with pytest.raises(ValueError):
        NoiseCoefficients(N=-1.0)


# ------------------------------------------------------------------------------ the chain
PROCEDURE = "procedure: static-capture\nsteps:\n  - capture:\n      duration: 1 h\n      label: static\n"
#: the starting set: SI, the declared_only profile's B with per-axis N and K raised ten-fold (so
#: that one hour resolves it, as in test_allan_kalibr)
GYRO = triad("gyro", "test", N=[1.22e-4, 1.5e-4, 1.0e-4], B=3.88e-5, K=1.0e-5)
ACCEL = triad("accel", "test", N=[5.9e-4, 7.5e-4, 4.5e-4], B=1.47e-4, K=3.0e-5)


@pytest.fixture(scope="module")
def chain(declared_only_hour_allan, tmp_path_factory) -> tuple[Path, dict]:
    """The capture on GYRO and ACCEL (conftest's declared_only_hour) and its `rigctl allan`
    (conftest's declared_only_hour_allan: the defaults, in process -- the stored results are
    tested, not the process; test_allan_kalibr checks that run's exports): a copy of the
    analysed recording here, and /truth's imu."""
    rec, truth, _ = declared_only_hour_allan
    return copy_recording(rec, tmp_path_factory.mktemp("noise_chain")), truth


def test_config_to_emulator_to_recording_to_allan_to_calibration(chain) -> None:
    rec, truth = chain
    given = {"gyro": GYRO, "accel": ACCEL}
    # the emulator ran on exactly the config's coefficients (its /truth, as to_json wrote them)
    for sensor, axes in given.items():
        emulated = tuple(from_json(d) for d in truth[f"{sensor}_noise"])
        assert [replace(m, source="test") for m in emulated] == list(axes)
        assert all(d["units"] == SI_UNITS[sensor] for d in truth[f"{sensor}_noise"])
    with h5py.File(rec, "r") as f:
        fitted = load_noise(f, rec)
        nf, nw, how = _noise(f, "allan", rec)  # what `rigctl calibrate --noise allan` uses
    assert how.startswith("from /results/allan")
    assert nf == tuple(fitted[a] for a in ("ax", "ay", "az")) and nw == tuple(fitted[a] for a in ("gx", "gy", "gz"))
    for sensor, model in (("accel", nf), ("gyro", nw)):
        for i, (m, m0) in enumerate(zip(model, given[sensor])):
            assert type(m) is type(m0) is NoiseCoefficients
            assert m.sensor == m0.sensor == sensor and to_json(m)["units"] == to_json(m0)["units"] == SI_UNITS[sensor]
            assert m.N.resolved and m.N.ci95 is not None
            assert abs(m.N.value / m0.N.value - 1.0) < 0.05, (sensor, i, m.N, m0.N)
            for t in ("B", "K"):
                c, true = getattr(m, t), m0.value(t)
                if c.resolved:
                    assert c.ci95[0] <= true <= c.ci95[1], (sensor, i, t, c, true)
                else:
                    assert c.upper95 is not None and true <= c.upper95, (sensor, i, t, c, true)
