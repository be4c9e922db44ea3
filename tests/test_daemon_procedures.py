"""10,000 generated procedure files (hypothesis): loading never raises anything but an
InputError naming the file and line, and demands outside the rig's limits are refused at load
time -- before the engine, and so before any motion."""
from __future__ import annotations

import re

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rigctl.config.config import load_config
from rigctl.engine.procedure import load_procedure
from rigctl.yamlio import InputError

from helpers import ROOT

CFG = load_config(ROOT / "configs" / "sim.yaml")
RATE_LIMIT_DPS = 300.0  # outer/middle axes of configs/sim.yaml (inner 500)

durations = st.one_of(st.sampled_from(["1 s", "5 min", "2 h", "0 s", "-3 s", "15 mn", "abc", ""]),
                      st.floats(-10, 1e5, allow_nan=False), st.integers(-5, 100), st.none(), st.booleans())
numbers = st.one_of(st.floats(-1000, 1000, allow_nan=False), st.integers(-1000, 1000),
                    st.sampled_from(["x", None, True, [1, 2]]))
angles = st.one_of(st.lists(numbers, min_size=0, max_size=4), numbers)
settle = st.one_of(st.none(), st.fixed_dictionaries({}, optional={
    "hold": durations, "timeout": durations, "position_window_deg": numbers,
    "rate_window_dps": numbers, "bogus": numbers}))


def step_strategy():
    warmup = st.fixed_dictionaries({"duration": durations}, optional={"angles_deg": angles, "label": st.text(max_size=8)})
    capture = st.fixed_dictionaries({"duration": durations}, optional={"settle": settle, "discard": durations})
    wait = st.fixed_dictionaries({"duration": durations}, optional={"prompt": st.text(max_size=10)})
    orient = st.fixed_dictionaries({}, optional={
        "angles_deg": st.lists(angles, max_size=4), "pattern": st.sampled_from(["24-position", "12"]),
        "sample": durations, "settle": settle, "count": numbers})
    rates = st.fixed_dictionaries({"rates_dps": st.one_of(
        st.lists(st.floats(-50, 800, allow_nan=False), min_size=1, max_size=3), numbers)}, optional={
        "axes": st.one_of(st.lists(st.sampled_from(["x", "y", "z", "w"]), min_size=1, max_size=3), numbers),
        "directions": st.lists(st.sampled_from(["forward", "reverse", "up"]), min_size=1, max_size=2),
        "dwell": durations, "revolutions": numbers, "discard": durations})
    taps = st.fixed_dictionaries({"count": numbers}, optional={"duration": durations})
    solve = st.fixed_dictionaries({"solvers": st.lists(st.sampled_from(["allan", "accel24", "magic"]), max_size=2)})
    kinds = {"warmup": warmup, "capture": capture, "wait": wait, "orientations": orient,
             "rates": rates, "taps": taps, "solve": solve, "teleport": warmup}
    return st.one_of(*[st.builds(lambda b, k=k: {k: b}, v) for k, v in kinds.items()],
                     st.sampled_from([None, 3, "warmup", {"a": 1, "b": 2}]))


procedures = st.fixed_dictionaries(
    {"steps": st.one_of(st.lists(step_strategy(), max_size=5), numbers)},
    optional={"procedure": st.text(max_size=6), "description": st.text(max_size=6),
              "parameters": st.dictionaries(st.sampled_from(["a", "b", "1x"]), numbers, max_size=2),
              "stepz": numbers})


def mutate(text: str, data) -> str:
    """Sometimes cut, duplicate or garble part of the text (YAML syntax errors, bad indents)."""
    if not text or not data.draw(st.booleans(), label="mutate"):
        return text
    i = data.draw(st.integers(0, len(text) - 1), label="at")
    j = data.draw(st.integers(i, min(len(text), i + 12)), label="to")
    junk = data.draw(st.sampled_from(["", ":", "- ", "  ", "\t", "{", "]", "'", "&a", "*b", "!!python/object:os.system ", "${x}"]))
    return text[:i] + junk + text[j:]


def too_fast(proc_obj) -> bool:
    """Does the (unmutated) procedure contain a rate demand beyond the outer/middle limit?"""
    steps = proc_obj.get("steps")
    if not isinstance(steps, list):
        return False
    for s in steps:
        if isinstance(s, dict) and "rates" in s and isinstance(s["rates"].get("rates_dps"), list):
            axes = s["rates"].get("axes", ["x", "y", "z"])
            if isinstance(axes, list) and any(a in ("y", "z") for a in axes) and \
                    any(r > RATE_LIMIT_DPS for r in s["rates"]["rates_dps"]):
                return True
    return False


#: Errors exempted from "names file and line": none (whole-file errors point at line 1 or at 'steps').
KNOWN_GAPS: tuple[str, ...] = ()
FILES_PER_EXAMPLE = 2
EXAMPLES = 5_000  # x 2 files = 10,000 generated procedure files


def check_one(path, obj, data) -> None:
    text = yaml.safe_dump(obj, sort_keys=False)
    mutated = mutate(text, data)
    # a new file each time: rewriting one in place (truncate, then write) makes ext4 flush its
    # blocks at the close (auto_da_alloc), ~2.5 ms of waiting per file, 10,000 times
    path.unlink(missing_ok=True)
    path.write_text(mutated)
    try:
        proc = load_procedure(path, limits=CFG.limits)
    except InputError as exc:  # anything else is a traceback for the user: fails the test
        for line in str(exc).splitlines():
            if any(re.match(g.format(path=re.escape(str(path))), line) for g in KNOWN_GAPS):
                continue
            assert re.match(rf"^{re.escape(str(path))}:\d+: \S", line), line
        return
    if mutated == text:
        assert not too_fast(obj), "a rate beyond the table's limit was accepted"
    for step in proc.steps:  # whatever loaded is inside the rig's limits: nothing can move wrongly
        CFG.limits.check(step.angles, step.rates)


@settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                 HealthCheck.function_scoped_fixture])
@given(objs=st.lists(procedures, min_size=FILES_PER_EXAMPLE, max_size=FILES_PER_EXAMPLE), data=st.data())
def test_generated_procedures_fail_only_with_file_and_line(objs, data, tmp_path_factory):
    for k, obj in enumerate(objs):
        check_one(tmp_path_factory.getbasetemp() / f"generated-{k}.yaml", obj, data)


@pytest.mark.parametrize("text", ["", "steps: []\n", "just a string\n"])
def test_whole_file_errors_name_file_and_line(tmp_path, text):
    path = tmp_path / "p.yaml"
    path.write_text(text)
    with pytest.raises(InputError) as err:
        load_procedure(path, limits=CFG.limits)
    assert re.match(rf"^{re.escape(str(path))}:\d+: ", str(err.value))
