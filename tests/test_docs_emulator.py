"""docs/emulator.md stays true: its YAML examples load through the real config loader and open
as an emulated rig that moves, samples (and taps), its overrides reach the truth, its Python
examples run, and every key of the profile file, the table's servo keys, the tap keys and the
fault kinds are documented."""
from __future__ import annotations

import json
import math
import re
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from rigctl.config.config import load_config
from rigctl.devices import AxisStatus
from rigctl.engine.procedure import load_procedure
from rigctl.engine.rig import open_rig
from rigctl.sim import faults as sim_faults
from rigctl.sim import taps as sim_taps
from rigctl.sim import tap_rig
from rigctl.sim.world import SERVO_KEYS

from helpers import ROOT

DOC = ROOT / "docs" / "emulator.md"
PROFILES = ROOT / "configs" / "imu-profiles.yaml"
TEXT = DOC.read_text(encoding="utf-8")
BLOCKS = [(m.group(1), m.group(2)) for m in re.finditer(r"```(yaml|python)\n(.*?)```", TEXT, re.S)]
YAML_BLOCKS = [b for lang, b in BLOCKS if lang == "yaml"]
PY_BLOCKS = [b for lang, b in BLOCKS if lang == "python"]

RIG = "# rig config"
FRAGMENT = re.compile(r"# fragment of (configs/[\w.-]+\.yaml): ([\w.]+)\s*$")
PROFILE_FILE = re.compile(r"# profiles file: ([\w.-]+\.yaml)\s*$")
#: keys the error model reads that no shipped profile spells out (documented as optional)
OPTIONAL_PROFILE_PATHS = {("power_on_time_s",), ("description",), ("rate_hz",),
                          ("gyro", "noise", "flicker_pairs_per_decade"),
                          ("accel", "noise", "flicker_pairs_per_decade"),
                          ("effects", "warmup", "T_ref_degC")}


def _first_line(block: str) -> str:
    return block.splitlines()[0] if block.strip() else ""


def _config_blocks() -> list[tuple[int, str]]:
    return [(i, b) for i, b in enumerate(YAML_BLOCKS)
            if _first_line(b) == RIG or FRAGMENT.match(_first_line(b))]


def _profile_files() -> dict[str, str]:
    out = {}
    for b in YAML_BLOCKS:
        m = PROFILE_FILE.match(_first_line(b))
        if m:
            out[m.group(1)] = b
    return out


def _paths(node: Any, prefix: tuple[str, ...] = ()) -> set[tuple[str, ...]]:
    """Every key path of a nested mapping (intermediate paths included)."""
    out: set[tuple[str, ...]] = set()
    if isinstance(node, dict):
        for k, v in node.items():
            p = (*prefix, str(k))
            out.add(p)
            out |= _paths(v, p)
    return out


def _known_profile_paths() -> set[tuple[str, ...]]:
    known = set(OPTIONAL_PROFILE_PATHS)
    docs = [yaml.safe_load(PROFILES.read_text())] + [yaml.safe_load(t) for t in _profile_files().values()]
    for d in docs:
        for prof in d["profiles"].values():
            known |= _paths(prof)
    return known


def _write_config(block: str, where: Path) -> Path:
    """The block as a config file in ``where`` (a fragment replaces its section of the named file)."""
    head = _first_line(block)
    data = yaml.safe_load(block)
    m = FRAGMENT.match(head)
    if m:
        frag = data
        data = yaml.safe_load((ROOT / m.group(1)).read_text())
        keys = m.group(2).split(".")
        node = data
        for k in keys[:-1]:
            node = node.setdefault(k, {})
        node[keys[-1]] = frag
    for name, text in _profile_files().items():
        (where / name).write_text(text)
    out = where / "doc-config.yaml"
    out.write_text(yaml.safe_dump(data))
    return out


def _settle(rig: Any, angles_deg: list[float], timeout_s: float = 15.0) -> float:
    """Move and wait (virtual time) until every axis reports target reached; returns the time."""
    rig.table.move(np.radians(angles_deg))
    t = 0.0
    while t < timeout_s:
        rig.clock.sleep(0.05)
        t += 0.05
        state = rig.table.read()
        if all(int(s) & AxisStatus.TARGET_REACHED for s in state.status):
            return t
    raise AssertionError(f"table did not reach {angles_deg} within {timeout_s} s: {state}")


def _check_overrides_reach_truth(imu_sim: dict, truth_imu: dict) -> None:
    over = imu_sim.get("overrides") or {}
    known = _known_profile_paths()
    for path in _paths(over):
        assert path in known, f"override key {'.'.join(path)} is not a profile key the emulator reads"
    for name, eff in (over.get("effects") or {}).items():
        got = truth_imu["effects"][name]
        if eff.get("enabled") is False:
            assert got == {"enabled": False}, name
            continue
        assert got["enabled"] is True, f"effect {name} should be on"
        for k, v in eff.items():
            assert np.allclose(got[k], v), (name, k, got[k], v)
    for sensor in ("gyro", "accel"):
        for k, v in (over.get(sensor) or {}).items():
            if f"{sensor}_{k}" in truth_imu:
                assert np.allclose(truth_imu[f"{sensor}_{k}"], v), (sensor, k)


def test_every_block_is_classified():
    assert len(_config_blocks()) >= 6, "the examples section lost its configs"
    for b in YAML_BLOCKS:
        head = _first_line(b)
        assert head == RIG or FRAGMENT.match(head) or PROFILE_FILE.match(head), \
            f"yaml block without a '# rig config' / '# fragment of ...' / '# profiles file: ...' line: {head!r}"
    for b in PY_BLOCKS:
        compile(b, "docs/emulator.md", "exec")  # every Python example is at least valid Python


@pytest.mark.parametrize("index,block", _config_blocks(), ids=lambda x: str(x) if isinstance(x, int) else "")
def test_config_example_runs(index: int, block: str, tmp_path: Path):
    cfg_path = _write_config(block, tmp_path)
    cfg = load_config(cfg_path)
    assert cfg.is_simulated and cfg.clock == "virtual"
    raw = yaml.safe_load(cfg_path.read_text())
    imu_sim = raw["imu"].get("sim") or {}
    with open_rig(cfg) as (rig, truth):
        json.dumps(truth)  # what the recorder writes into /truth
        _settle(rig, [90.0, -45.0, 30.0])
        rig.imu.read()
        t0 = rig.clock.now()
        rig.clock.sleep(2.0)
        block_ = rig.imu.read()
        n = len(block_.time)
        assert 0.95 * 2.0 * cfg.imu_rate_hz <= n <= 2.0 * cfg.imu_rate_hz + 1
        assert np.all(np.diff(block_.counter.astype(np.int64)) >= 1)
        assert block_.time[0] >= t0 - 0.5 and block_.time[-1] <= rig.clock.now() + 1e-9
        for arr in (block_.specific_force, block_.angular_rate, block_.temperature):
            assert np.all(np.isfinite(arr))
        g = np.linalg.norm(block_.specific_force.mean(axis=0))
        assert abs(g - cfg.gravity) < 0.1 * cfg.gravity, g  # at rest: gravity, whatever the errors
        assert np.linalg.norm(block_.angular_rate.mean(axis=0)) < 0.1  # rad/s: Earth rate + biases
        if "profile" in imu_sim:
            assert truth["imu"]["output_rate_hz"] == cfg.imu_rate_hz
            _check_overrides_reach_truth(imu_sim, truth["imu"])
            if imu_sim["profile"] == "random":
                seed = imu_sim.get("seed", raw.get("seed", 0))
                assert truth["imu"]["profile_name"].startswith("random(") and f"seed={seed}" in truth["imu"]["profile_name"]
        t_sim = (raw.get("table") or {}).get("sim") or {}
        for k, v in t_sim.items():
            if k in truth["table"]["axes"][0]:
                vals = v if isinstance(v, list) else [v] * 3
                assert [ax[k] for ax in truth["table"]["axes"]] == pytest.approx(vals), k
        if cfg.pulses.driver == "sim":
            p_sim = raw["pulses"].get("sim") or {}
            taps = truth["pulses"]["taps"]
            for k, v in p_sim.items():
                if k in taps and k != "axis":
                    assert taps[k] == (v if isinstance(v, str) else pytest.approx(v)), k
            proc_path = tmp_path / "taps.yaml"
            proc_path.write_text("procedure: doc-taps\nsteps:\n  - taps: {count: 4, duration: 16 s}\n")
            step = load_procedure(proc_path, limits=cfg.limits).steps[0]
            assert step.expected_taps == 4
            rig.imu.read()
            rig.clock.sleep(1.0)
            quiet = rig.imu.read()
            t_start = rig.clock.now()
            rig.operator.prompt(step, t_start, step.sample_s)
            rig.clock.sleep(step.sample_s + 1.0)
            tapped = rig.imu.read()
            pulses = rig.pulses.read().time
            assert pulses.size >= 1
            assert np.all((pulses > t_start) & (pulses < t_start + step.sample_s))
            assert np.all(np.diff(pulses) >= taps["timeguard_s"])
            if not (taps["missed_probability"] or taps["spurious_pulses"]):  # bounces < timeguard
                assert pulses.size == 4 - min(taps["missed_count"], 4)
            axis = taps["axis"]
            jump = np.max(np.abs(np.diff(tapped.specific_force[:, axis])))
            calm = np.max(np.abs(np.diff(quiet.specific_force[:, axis])))
            assert jump > 10 * calm, "taps not visible in the IMU output"
            rows = truth.drain_truth_rows()  # what the recorder appends to /truth/taps, /edges
            assert int(rows["taps"]["hammer"].sum()) == 4
            logged = rows["edges"]["logged"] == 1
            assert np.array_equal(np.sort(rows["edges"]["time_s"][logged]), pulses)


@pytest.mark.parametrize("index", [i for i, b in enumerate(PY_BLOCKS) if b.startswith("# runnable")])
def test_python_example_runs(index: int, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.chdir(ROOT)
    exec(compile(PY_BLOCKS[index], f"docs/emulator.md python block {index}", "exec"), {"__name__": "doc"})


def _doc_keys() -> set[str]:
    return set(re.findall(r"`([^`\s]+)`", TEXT))


def test_every_effect_is_documented():
    doc = yaml.safe_load(PROFILES.read_text())
    effects = {name for prof in doc["profiles"].values() for name in (prof.get("effects") or {})}
    assert effects, "no effects found in configs/imu-profiles.yaml"
    keys = _doc_keys()
    missing = sorted(e for e in effects if e not in keys or f"### `{e}`" not in TEXT)
    assert not missing, f"effects without a section in docs/emulator.md: {missing}"


def test_every_profile_key_is_documented():
    doc = yaml.safe_load(PROFILES.read_text())
    paths = set()
    for prof in doc["profiles"].values():
        paths |= _paths(prof)
    names = {p[-1] for p in paths} | set(doc["random"]) | {"profiles", "random"}
    missing = sorted(n for n in names if n not in _doc_keys() and f"random.{n}" not in _doc_keys())
    assert not missing, f"profile keys not in docs/emulator.md: {missing}"


def _schema_keys(schema: dict) -> set[str]:
    out = set()
    for k, v in schema.items():
        out.add(k)
        if isinstance(v, dict):
            out |= _schema_keys(v)
    return out


def test_every_schema_key_is_documented():
    """Every key the profile checker accepts (a misspelling of any other is an error) has a
    row in docs/emulator.md, and so does every column of the truth tables (also in
    docs/data-format.md)."""
    from rigctl.sim.profiles import PROFILE_SCHEMA, RANDOM_SCHEMA

    keys = _doc_keys()
    names = _schema_keys(PROFILE_SCHEMA) - {"name"}  # 'name' is set by the loader
    missing = sorted(n for n in names | set(RANDOM_SCHEMA)
                     if n not in keys and f"random.{n}" not in keys)
    assert not missing, f"schema keys not in docs/emulator.md: {missing}"
    fmt = (DOC.parent / "data-format.md").read_text(encoding="utf-8")
    for table, cols in tap_rig.TRUTH_TABLES.items():
        for col in cols:
            assert f"`/truth/{table}/{col}`" in TEXT and f"`/truth/{table}/{col}`" in fmt, (table, col)


def test_table_tap_and_fault_keys_are_documented():
    tap_keys = [f.name for f in fields(sim_taps.TapParams) if f.name != "range_m_s2"]
    names = [*SERVO_KEYS, *tap_keys, *tap_rig.EXTRA_KEYS, *sim_faults.KINDS]
    missing = sorted(n for n in names if n not in _doc_keys())
    assert not missing, f"keys not in docs/emulator.md: {missing}"


def test_servo_example_timing():
    """Section 6's example on configs/sim.yaml: 90 deg on the outer axis, profile complete at
    1.34 s with the axis 0.32 deg past the target, target reached at 1.92 s."""
    assert "a 90 deg move is a 1.34 s triangle" in TEXT and "comes at 1.92 s" in TEXT
    cfg = load_config(ROOT / "configs" / "sim.yaml")
    t_pc = t_tr = over = None
    with open_rig(cfg) as (rig, _):
        rig.table.move(np.radians([90.0, 0.0, 0.0]))
        for _ in range(400):
            rig.clock.sleep(0.005)
            st = rig.table.read()
            s = int(st.status[0])
            if t_pc is None and s & AxisStatus.PROFILE_COMPLETE:
                t_pc, over = st.time, math.degrees(st.angle[0]) - 90.0
                assert not s & AxisStatus.TARGET_REACHED
            if s & AxisStatus.TARGET_REACHED:
                t_tr = st.time
                break
    t_end = 2 * math.sqrt(90.0 / 200.0)  # triangle at 200 deg/s^2: 1.342 s
    assert round(t_end, 2) == 1.34
    assert t_end <= t_pc < t_end + 1 / cfg.imu_rate_hz + 1e-9  # first sample of the grid after it
    assert over == pytest.approx(0.32, abs=0.005)
    assert t_tr == pytest.approx(1.92, abs=0.01)


def test_worked_numbers():
    """The numbers quoted in the text: 3.1 mg centripetal at 100 deg/s and 1 cm; the servo lag."""
    w = math.radians(100.0)
    assert "3.05e-2 m/s^2 = 3.1 mg" in TEXT
    assert w * w * 0.01 == pytest.approx(3.05e-2, rel=2e-3)
    assert w * w * 0.01 / 9.80665e-3 == pytest.approx(3.1, abs=0.05)
    assert "still 0.32 deg" in TEXT
    assert 200.0 / (2 * math.pi * 4.0) ** 2 == pytest.approx(0.32, abs=0.005)


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_internal_links_resolve_and_index_lists_the_doc():
    anchors = {_slug(h) for h in re.findall(r"^#+ (.+)$", TEXT, re.M)}
    links = re.findall(r"\]\(#([^)]+)\)", TEXT)
    assert links and not [a for a in links if a not in anchors]
    for target in re.findall(r"\]\(([\w.-]+\.md)\)", TEXT):
        assert (DOC.parent / target).is_file(), target
    assert "(emulator.md)" in (DOC.parent / "README.md").read_text()
