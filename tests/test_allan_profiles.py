"""Issue 15's first Done-when, cheap: 1 h of every emulator profile (the default IMU and each
of configs/imu-profiles.yaml, full error model, static) through the Allan pipeline with
--taus octave and all. The checks are benchmarks/allan_profiles.py's, which read the curve
with plain numpy (not the fit's own bookkeeping): no term given as a bound above what the
curve allows (B <= min sigma / 0.664, N, K, Q, R likewise); every informative tau where the
fitted total leaves the 95 % band named by the self-check; octave and all agree within their
95 % intervals on every axis whose self-checks both pass. The 12 h run of the Done-when is the
benchmark (benchmarks/allan_profiles.py, figures in docs/allan.md)."""
from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _bench():
    spec = importlib.util.spec_from_file_location("allan_profiles",
                                                  ROOT / "benchmarks" / "allan_profiles.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_every_profile_one_hour(tmp_path: Path, capsys) -> None:
    b = _bench()
    from rigctl.sim.profiles import profile_names

    cases = ["default"] + [p for p in profile_names() if p != "random"]
    assert len(cases) >= 5
    t = b.run_cases(cases, 1.0, ("octave", "all"), str(tmp_path))
    out = capsys.readouterr().out
    assert t["fits"] == 2 * 6 * len(cases)
    assert t["over_limit"] == 0, t["over_where"]
    assert t["informative"] > 1000 and t["unnamed"] == 0, t["unnamed_where"]
    assert t["pairs"] == 6 * len(cases)
    assert t["disagree_checks_ok"] == 0, t["disagree_where"]
    assert "== tactical (emulated, 1 h)" in out
