"""The closed loop on table-less sessions from an independent generator (tests/pose_session_synth.py:
imports nothing from rigctl), each written as CSV, brought in with `rigctl import` and calibrated.

Criteria (issue 14): each testable effect named in the right sub-model in at least 9 of 10 seeds;
two effects outside the library: nothing claimed and UNEXPLAINED RESIDUAL in at least 9 of 10
seeds; 20 clean seeds: at most one false flag. The counts are printed (pytest -s) so a run
reports what it measured, not only pass/fail.
"""
from __future__ import annotations

import contextlib
import io
import os
from concurrent.futures import ProcessPoolExecutor

import pytest

import pose_session_synth as S
from rigctl.analysis.pose_calibration import calibrate_poses
from rigctl.cli import main

SEEDS = range(10)


def _run(tmp_path, seed: int, effect: str | None, amplitude: float = 1.0) -> dict:
    """Generate, import and calibrate one session; the facts the tests look at."""
    csv = S.write_csv(tmp_path / f"s{seed}_{effect}_{amplitude}.csv", seed, effect, amplitude=amplitude)
    rec = csv.with_suffix(".h5")
    with contextlib.redirect_stdout(io.StringIO()):
        rc = main(["import", str(csv), "-o", str(rec), "--columns",
                   "time=t,acc_x=ax,acc_y=ay,acc_z=az,gyr_x=gx,gyr_y=gy,gyr_z=gz,temp=temp", "--units",
                   "acc=m/s^2,gyr=rad/s,time=s", "--rate", "100", "--segments", str(csv.with_suffix(".json")),
                   "--latitude-deg", "45", "--gravity", str(S.G)])
    assert rc in (0, None)
    payload, _, _ = calibrate_poses(rec)
    return {"status": payload["status"],
            "claims": {k: v["effects_claimed"] for k, v in payload["closed_loop"].items()},
            "ambiguous": [f for v in payload["closed_loop"].values() for f in v["findings"]
                          if f.startswith("ambiguous")]}


def _many(tmp_path, jobs: list[tuple[int, str | None, float]]) -> list[dict]:
    """Sessions in parallel on the machine's cores (each is independent)."""
    with ProcessPoolExecutor(max_workers=max(1, min(4, os.cpu_count() or 1))) as ex:
        return list(ex.map(_run, [tmp_path] * len(jobs), *zip(*jobs)))


@pytest.mark.parametrize("effect", sorted(S.IN_LIBRARY))
def test_in_library_effect_named(tmp_path, effect):
    subs = S.IN_LIBRARY[effect]
    subs = (subs,) if isinstance(subs, str) else subs
    named, honest, other = 0, 0, []
    for p in _many(tmp_path, [(seed, effect, 1.0) for seed in SEEDS]):
        c = p["claims"]
        # the cross-coupling's split between the axes (accel_cross_quadratic_split) is part of it
        wrong = [e for k, v in c.items() for e in v if e != effect and not e.startswith(effect + "_")]
        other += wrong
        hit = any(effect in c.get(sub, []) for sub in subs)
        named += hit
        honest += (hit or any(effect in a for a in p["ambiguous"])
                   or p["status"] == "UNEXPLAINED RESIDUAL") and not wrong
    print(f"\n{effect}: named in {named}/10 seeds; named, ambiguous or unexplained without a wrong "
          f"claim in {honest}/10; other claims: {other}")
    assert honest >= 9, (honest, other)  # never misnamed
    assert named >= 9, (named, other)


@pytest.mark.parametrize("effect", ["accel_quadratic", "accel_scale_asymmetry"])
def test_near_collinear_effects_at_a_third_of_the_amplitude(tmp_path, effect):
    """u^3 and u |u| are nearly collinear in the magnitude: at a third of the amplitude 40 poses
    barely separate them. The loop then mostly says "ambiguous" or names the right one; measured
    over these 10 sessions, it named the other one once (a chance beyond the 95 % margin)."""
    other = "accel_scale_asymmetry" if effect == "accel_quadratic" else "accel_quadratic"
    named = amb = wrong = 0
    for p in _many(tmp_path, [(seed, effect, 1 / 3) for seed in range(5)]):
        c = p["claims"]["accel"]
        named += effect in c
        wrong += other in c
        amb += any(effect in a and other in a for a in p["ambiguous"])
    print(f"\n{effect} at 1/3 amplitude: named {named}, ambiguous {amb}, the other named {wrong} (of 5)")
    assert wrong <= 1 and named + amb >= 4


@pytest.mark.parametrize("effect", S.OUTSIDE)
def test_outside_library_effect_not_misnamed(tmp_path, effect):
    good = 0
    for p in _many(tmp_path, [(seed, effect, 1.0) for seed in SEEDS]):
        claimed = [e for v in p["claims"].values() for e in v]
        good += not claimed and p["status"] == "UNEXPLAINED RESIDUAL"
    print(f"\n{effect}: nothing claimed and UNEXPLAINED RESIDUAL in {good}/10 seeds")
    assert good >= 9


def test_clean_sessions_at_most_one_false_flag(tmp_path):
    flags = []
    for seed, p in enumerate(_many(tmp_path, [(100 + seed, None, 1.0) for seed in range(20)])):
        claimed = [e for v in p["claims"].values() for e in v]
        if claimed or p["status"] != "OK":
            flags.append((100 + seed, p["status"], claimed))
    print(f"\nclean: {len(flags)} false flags in 20 seeds: {flags}")
    assert len(flags) <= 1
