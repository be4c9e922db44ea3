"""Procedure language: shipped procedures compile; broken files give errors naming their line."""
import math
from pathlib import Path

import numpy as np
import pytest

from rigctl.config.config import load_config
from rigctl.engine.estimate import estimate
from rigctl.engine.procedure import load_procedure, parse_overrides
from rigctl.yamlio import InputError

from helpers import run_rigctl

ROOT = Path(__file__).resolve().parent.parent
PROC = ROOT / "procedures"


@pytest.fixture(scope="module")
def cfg():
    return load_config(ROOT / "configs" / "sim.yaml")


def test_24pos_has_warmup_and_24_orientations(cfg):
    p = load_procedure(PROC / "24pos.yaml", limits=cfg.limits)
    kinds = [s.kind for s in p.steps]
    assert kinds.count("warmup") == 1 and kinds.count("orientation") == 24
    assert p.steps[0].sample_s == 15 * 60
    labels = {s.label for s in p.steps if s.kind == "orientation"}
    assert len(labels) == 24


def test_rates_has_18_windows_of_whole_revolutions():
    p = load_procedure(PROC / "rates.yaml")
    rates = [s for s in p.steps if s.kind == "rate"]
    assert len(rates) == 18
    mags = sorted({round(math.degrees(np.nanmax(np.abs(s.rates)))) for s in rates})
    assert mags == [40, 63, 100]
    for s in rates:
        w = np.nanmax(np.abs(s.rates))
        assert s.sample_s * w == pytest.approx(2 * 2 * math.pi)  # 2 revolutions
        assert np.sum(~np.isnan(s.rates)) == 1
    signs = [np.sign(np.nansum(s.rates)) for s in rates]
    assert signs.count(1) == 9 and signs.count(-1) == 9


def test_full_calibration_estimate(cfg):
    p = load_procedure(PROC / "full-calibration.yaml", limits=cfg.limits)
    est = estimate(p.steps, cfg)
    total = sum(e.total_s for e in est)
    kinds = [s.kind for s in p.steps]
    assert kinds.count("orientation") == 24 and kinds.count("rate") == 18 and kinds[-1] == "solve"
    # 15 min warm-up + 24 x (30 s sample + settle + moves) + 18 short windows
    assert 15 * 60 + 24 * 33 < total < 15 * 60 + 24 * 60 + 18 * 30


def test_allan_overnight_is_12_hours():
    p = load_procedure(PROC / "allan-overnight.yaml")
    cap = [s for s in p.steps if s.kind == "capture"]
    assert len(cap) == 1 and cap[0].sample_s == 12 * 3600


def test_parameter_override_reaches_included_file():
    p = load_procedure(PROC / "24pos.yaml", parse_overrides(["warmup=5 min", "sample=10"]))
    assert p.steps[0].sample_s == 300
    assert p.steps[1].sample_s == 10
    with pytest.raises(InputError, match="no parameter 'nope'"):
        load_procedure(PROC / "24pos.yaml", {"nope": 1})


BROKEN = {
    "unknown_key": """procedure: t
steps:
  - warmup:
      duration: 10 s
      durration: 5 s   # <-
""",
    "wrong_type": """procedure: t
steps:
  - capture:
      duration: ten minutes   # <-
""",
    "missing_field": """procedure: t
steps:
  - capture:             # <-
      label: no duration
""",
    "unknown_kind": """procedure: t
steps:
  - warmup: {duration: 1 s}
  - warmpu: {duration: 1 s}   # <-
""",
    "rate_over_limit": """procedure: t
steps:
  - rates:
      axes: [z]
      rates_dps: [40, 900]   # <-
""",
    "angle_not_triplet": """procedure: t
steps:
  - orientations:
      angles_deg:
        - [0, 0, 0]
        - [90, 0]    # <-
""",
    "yaml_syntax": """procedure: t
steps:
  - warmup: {duration: 1 s
  - capture: {duration: 2 s}   # <-
""",
    "unknown_parameter": """procedure: t
steps:
  - warmup:
      duration: ${warm}   # <-
""",
    "negative_duration": """procedure: t
steps:
  - wait:
      duration: -3 s   # <-
""",
    "unknown_solver": """procedure: t
steps:
  - solve:
      solvers:
        - accel24
        - kalman   # <-
""",
    "bad_settle_key": """procedure: t
defaults:
  settle: {hold: 1 s, window: 2}   # <-
steps:
  - capture: {duration: 1 s}
""",
    "missing_include": """procedure: t
steps:
  - include: nowhere.yaml   # <-
""",
}


@pytest.mark.parametrize("name", sorted(BROKEN))
def test_broken_procedure_names_file_and_line(name, tmp_path, cfg):
    text = BROKEN[name]
    path = tmp_path / f"{name}.yaml"
    path.write_text(text)
    expected_line = next(i for i, line in enumerate(text.splitlines(), 1) if "# <-" in line)
    with pytest.raises(InputError) as info:
        load_procedure(path, limits=cfg.limits)
    err = info.value
    assert err.file == str(path)
    assert err.line == expected_line, str(err)
    assert f"{path}:{expected_line}:" in str(err)


def test_every_solver_a_procedure_accepts_has_its_hook():
    """procedure.SOLVERS (what a solve step may name; the core cannot import the hooks) and
    solve.SOLVER_HOOKS (what runs) name the same solvers."""
    from rigctl.engine.procedure import SOLVERS
    from rigctl.run.solve import SOLVER_HOOKS
    assert sorted(SOLVERS) == sorted(SOLVER_HOOKS)


def test_include_cycle_is_reported(tmp_path):
    (tmp_path / "a.yaml").write_text("steps:\n  - include: b.yaml\n")
    (tmp_path / "b.yaml").write_text("steps:\n  - include: a.yaml\n")
    with pytest.raises(InputError, match="include cycle"):
        load_procedure(tmp_path / "a.yaml")


def test_several_errors_are_all_reported(tmp_path):
    path = tmp_path / "two.yaml"
    path.write_text("steps:\n  - capture: {duration: x}\n  - wait: {durat: 1}\n")
    with pytest.raises(InputError) as info:
        load_procedure(path)
    text = str(info.value)
    assert f"{path}:2:" in text and f"{path}:3:" in text


def test_yaml_tags_are_not_executed(tmp_path):
    path = tmp_path / "evil.yaml"
    path.write_text("steps:\n  - wait: !!python/object/apply:os.system ['echo pwned']\n")
    with pytest.raises(InputError) as info:
        load_procedure(path)
    assert info.value.line == 2


#: malformed procedures read by the typed step models: name -> (text, the message after
#: "FILE:LINE: ", where LINE is the line marked "# <-")
MALFORMED = {
    "step_key_did_you_mean": ("""steps:
  - capture:
      duration: 10 s
      discrad: 2 s   # <-
""", "unknown key 'discrad' in 'capture' (did you mean 'discard'?)"),
    "settle_key_did_you_mean": ("""steps:
  - rates:
      rates_dps: [10]
      settle:
        hodl: 1 s   # <-
""", "unknown key 'hodl' in 'settle' (did you mean 'hold'?)"),
    "parameter_key_did_you_mean": ("""parameters:
  warm:
    defualt: 5 s   # <-
steps:
  - warmup: {duration: "${warm}"}
""", "unknown key 'defualt' in parameter 'warm' (did you mean 'default'?)"),
    "solver_did_you_mean": ("""steps:
  - solve:
      solvers:
        - alan   # <-
""", "unknown solver 'alan' (did you mean 'allan'?)"),
    "duration_wrong_unit": ("""steps:
  - warmup:
      duration: 15 kg   # <-
""", "'duration': unknown time unit 'kg' in '15 kg'; use ms, s, min or h"),
    "sample_unit_on_a_number": ("""defaults:
  discard: 2 deg   # <-
steps:
  - orientations: {pattern: 24-position}
""", "'discard': unknown time unit 'deg' in '2 deg'; use ms, s, min or h"),
    "count_wrong_type": ("""steps:
  - taps:
      count: many   # <-
""", "'count' must be a number, got str 'many'"),
    "axes_wrong_type": ("""steps:
  - rates:
      rates_dps: [10]
      axes: z   # <-
""", "'axes' must be a list, got str 'z'"),
    "label_wrong_type": ("""steps:
  - wait:
      duration: 1 s
      label: [a, b]   # <-
""", "'label' must be text, got a list"),
    "chamber_rate_missing": ("""steps:
  - chamber-ramp:   # <-
      setpoint_c: 40
""", "'chamber-ramp' is missing 'rate_c_per_min' (add a line 'rate_c_per_min: ...')"),
}


@pytest.mark.parametrize("name", sorted(MALFORMED))
def test_malformed_procedure_message_names_file_line_and_fix(name, tmp_path):
    text, message = MALFORMED[name]
    path = tmp_path / f"{name}.yaml"
    path.write_text(text)
    line = next(i for i, ln in enumerate(text.splitlines(), 1) if "# <-" in ln)
    with pytest.raises(InputError) as info:
        load_procedure(path)
    assert str(info.value) == f"{path}:{line}: {message}"


def test_error_in_an_included_file_names_that_file_and_line(tmp_path):
    (tmp_path / "inner.yaml").write_text("steps:\n  - warmup: {duration: 1 s}\n  - wiat: {duration: 1 s}\n")
    (tmp_path / "outer.yaml").write_text("steps:\n  - include: inner.yaml\n")
    with pytest.raises(InputError) as info:
        load_procedure(tmp_path / "outer.yaml")
    assert str(info.value) == (f"{tmp_path / 'inner.yaml'}:3: unknown key 'wiat' in the step "
                               "(did you mean 'wait'?)")


def test_a_parameter_given_a_wrong_value_names_the_option_typed(tmp_path):
    """-p values are checked by the model of the key they land in; the error names the -p option
    the user typed (the key's file and line only as where it is used)."""
    path = tmp_path / "p.yaml"
    path.write_text("parameters:\n  n: 3\nsteps:\n  - taps:\n      count: ${n}\n")
    assert load_procedure(path, {"n": 5}).steps[0].expected_taps == 5
    with pytest.raises(InputError) as info:
        load_procedure(path, {"n": "lots"})
    assert str(info.value) == (f"-p n='lots': 'count' must be a number, got str 'lots' "
                               f"(parameter 'n' is used at {path}:5)")
    # a wrong default written in the file itself is still the file's line
    path.write_text("parameters:\n  n: lots\nsteps:\n  - taps:\n      count: ${n}\n")
    with pytest.raises(InputError) as info:
        load_procedure(path)
    assert str(info.value) == f"{path}:5: 'count' must be a number, got str 'lots'"


def test_a_bad_duration_option_on_the_command_line_is_one_line_naming_it():
    """`rigctl run procedures/24pos.yaml -p warmup=banana`: the value lands in the included
    warmup.yaml; the one console line names the option, exit 2, no traceback."""
    r = run_rigctl("run", "procedures/24pos.yaml", "-p", "warmup=banana", timeout=60)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("rigctl run: error: -p warmup='banana': cannot read 'banana' as a duration"), lines[0]
    assert "warmup.yaml:9" in lines[0] and "Traceback" not in r.stderr


def test_an_included_file_inherits_the_defaults_it_does_not_set(tmp_path):
    """defaults: merge key by key down the includes (the inner file's keys win for its steps)."""
    (tmp_path / "inner.yaml").write_text("defaults:\n  discard: 3 s\nsteps:\n  - orientations: {pattern: 24-position, axes: [x], count: 1}\n")
    (tmp_path / "outer.yaml").write_text("defaults:\n  sample: 7 s\n  discard: 2 s\n  settle: {hold: 4 s}\n"
                                         "steps:\n  - include: inner.yaml\n  - capture: {duration: 1 s}\n")
    inner, outer = load_procedure(tmp_path / "outer.yaml").steps
    assert (inner.sample_s, inner.discard_s, inner.settle.hold_s) == (7.0, 3.0, 4.0)
    assert (outer.discard_s, outer.settle.hold_s) == (2.0, 4.0)
