"""Issue 15's first Done-when, cheap: 1 h of every emulator profile (the default IMU and each
of configs/imu-profiles.yaml, full error model, static) through the Allan pipeline with
--taus octave and all. The checks are benchmarks/allan_profiles.py's, which read the curve
with plain numpy (not the fit's own bookkeeping): no term given as a bound above what the
curve allows (B <= min sigma / 0.664, N, K, Q, R likewise); every informative tau where the
fitted total leaves the 95 % band named by the self-check; octave and all agree within their
95 % intervals on every axis whose self-checks both pass (tones found before the fit: below).
The emulated captures start after procedures/warmup.yaml's 15 minutes, as allan-overnight's do.
The 12 h run of the Done-when is the benchmark (benchmarks/allan_profiles.py, figures in
docs/allan.md)."""
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
    # octave and all agree on every axis whose two checks pass. Until the tones were found
    # before the fit, consumer_mems ax Q was apart (--taus all: Q 7.7e-5 m/s [7.18e-5,
    # 8.33e-5]; octave: < 7.13e-5): its 47.3 Hz vibration tone, near the 100 Hz output's
    # Nyquist, adds a^2 sin^4(pi f m tau0) / (m sin(pi f tau0))^2 to sigma^2, ~a^2/m^2 at the
    # odd m and ~0 at the even m up to m ~ 9, so only the all-tau set saw a Q-like term. The
    # pipeline now finds the tone (Welch periodogram) and carries that term in the model
    ok_pairs = [w for w in t["disagree_where"] if w.endswith("(checks ok)")]
    assert len(ok_pairs) == t["disagree_checks_ok"]
    assert ok_pairs == [], t["disagree_where"]
    # ... because the tone was found: on every consumer_mems axis at 47.3 Hz (the emulator's
    # frequency, seen through its clock's 50 ppm drift), and on no axis of the profiles
    # without vibration (default, declared_only)
    cm = [w for w in t["tones"] if w.startswith("consumer_mems")]
    axes_47 = {w.split(":")[1] for w in cm if abs(float(w.split(":")[2][:-2]) - 47.3) < 0.01}
    assert axes_47 == {"gx", "gy", "gz", "ax", "ay", "az"}, t["tones"]
    assert not [w for w in t["tones"] if w.startswith(("default", "declared_only"))], t["tones"]
    assert "== tactical (emulated, 1 h, after 900 s warm-up)" in out
