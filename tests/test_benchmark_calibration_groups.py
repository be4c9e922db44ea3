"""benchmarks/calibration.py: the coverage per parameter group with its Clopper-Pearson interval
(allan_quickstart_cov.clopper_pearson, checked here against the binomial tails): the figures
docs/calibration.md quotes for the session noise model."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import scipy.optimize
import scipy.stats

ROOT = Path(__file__).resolve().parent.parent
_spec = importlib.util.spec_from_file_location("bench_calibration", ROOT / "benchmarks" / "calibration.py")
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)


def _exact_by_tails(k: int, n: int) -> tuple[float, float]:
    """The exact interval from its definition: the p at which the binomial tail beyond k is
    2.5 % (P(X >= k | p_lo) = 0.025, P(X <= k | p_hi) = 0.025), by root finding on the cdf."""
    lo = 0.0 if k == 0 else scipy.optimize.brentq(
        lambda p: scipy.stats.binom.sf(k - 1, n, p) - 0.025, 1e-12, 1 - 1e-12, xtol=1e-14)
    hi = 1.0 if k == n else scipy.optimize.brentq(
        lambda p: scipy.stats.binom.cdf(k, n, p) - 0.025, 1e-12, 1 - 1e-12, xtol=1e-14)
    return lo, hi


@pytest.mark.parametrize("k, n", [(0, 30), (28, 30), (30, 30), (87, 100), (171, 180), (341, 360)])
def test_clopper_pearson_matches_the_binomial_tails(k: int, n: int) -> None:
    lo, hi = bench.clopper_pearson(k, n)
    elo, ehi = _exact_by_tails(k, n)
    assert lo == pytest.approx(elo, abs=1e-9) and hi == pytest.approx(ehi, abs=1e-9)
    assert lo <= k / n <= hi


def test_the_27_declared_parameters_fall_in_their_groups() -> None:
    ax = "xyz"
    names = ([f"{s}_bias_{a}_{'m_s2' if s == 'accel' else 'rad_s'}" for s in ("accel", "gyro") for a in ax]
             + [f"{s}_M_{a}{b}_ratio" for s in ("accel", "gyro") for a in ax for b in ax]
             + [f"accel_quad_{a}_s2_per_m" for a in ax])
    got = [bench.param_group(n) for n in names]
    counts = {g: got.count(g) for g in bench.GROUPS}
    assert counts == {"accel_bias": 3, "gyro_bias": 3, "scale": 6, "misalignment": 12, "quadratic": 3}
    diag = [n for n in names if "_M_" in n and n.split("_M_")[1][0] == n.split("_M_")[1][1]]
    assert all(bench.param_group(n) == "scale" for n in diag) and len(diag) == int(np.sum(np.eye(3))) * 2


def _h5_run(path: Path, status: bytes, truth: dict | None) -> None:
    import json

    import h5py
    path.parent.mkdir(parents=True)
    with h5py.File(path, "w") as f:
        f.create_dataset("run/status", data=[status])
        if truth is not None:
            f.create_dataset("truth", data=0).attrs["params_json"] = json.dumps({"imu": truth})


def test_a_part_done_recording_is_passed_over(tmp_path: Path) -> None:
    """--recordings reuse: a recording an interrupted run left beside a complete one is never the
    one analysed, whichever sorts first; an unreadable file is passed over too."""
    out = tmp_path / "corr-tactical-3"
    _h5_run(out / "20261128T010000Z-bench-record" / "recording.h5", b"running", None)  # interrupted
    assert bench._complete_recording(out) is None
    _h5_run(out / "20261128T020000Z-bench-record" / "recording.h5", b"complete", {"seed": 3})  # the rerun
    rec, truth = bench._complete_recording(out)
    assert rec.parent.name.startswith("20261128T020000Z") and truth == {"seed": 3}
    (out / "20261128T030000Z-bench-record").mkdir()
    (out / "20261128T030000Z-bench-record" / "recording.h5").write_bytes(b"\x89HDF\r\n cut")
    assert bench._complete_recording(out)[1] == {"seed": 3}
    assert bench._complete_recording(tmp_path / "corr-tactical-4") is None
