"""The layers of docs/architecture.md, enforced: the import-linter contracts in pyproject.toml, the
list of CLI modules they protect, and the size of those CLI modules.

drivers/ and sim/ are installed as rigctl.drivers and rigctl.sim (package-dir in pyproject.toml),
so lint-imports, which reads the package's folder, would not see them under rigctl/ (under the
editable install they exist only in setuptools' finder hook: tests/lint_layers.py says why).
tests/lint_layers.py -- the command docs/architecture.md gives developers -- builds a tree with
rigctl/* linked in and each mapped sub-package linked at its installed place, and runs
lint-imports there with the repository's pyproject.toml; these tests use it. A second tree with
planted violations checks that every contract can fail, that drivers, sim and solvers are seen,
and that a module of rigctl/ in no layer is reported; the command itself is run as documented,
on this checkout and on one with a broken import.
"""
from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from lint_layers import link_tree, lint

ROOT = Path(__file__).resolve().parent.parent
PYPROJECT = ROOT / "pyproject.toml"
CONFIG = tomllib.loads(PYPROJECT.read_text())
CONTRACTS = {c["id"]: c for c in CONFIG["tool"]["importlinter"]["contracts"]}
CMD_MODULES = sorted(p.stem for p in (ROOT / "rigctl" / "commands").glob("*_cmd.py"))
#: pipelines on their way into rigctl.analysis (allan and calibration on other branches)
MOVING: set[str] = set()  # (allan_cmd: its pipeline is in rigctl/analysis/allan.py)


def test_the_contracts_hold(tmp_path: Path) -> None:
    r = lint(link_tree(tmp_path))
    assert r.returncode == 0, r.stdout[-6000:] + r.stderr[-3000:]
    assert f"{len(CONTRACTS)} kept, 0 broken" in r.stdout, r.stdout[-3000:]


def test_the_contracts_can_fail(tmp_path: Path) -> None:
    """Violations planted in solvers/, sim/, drivers/, analysis/, the engine and a foundation
    are each reported (and some close an import cycle), and so is a module in no layer."""
    planted = {
        "errors.py": "from rigctl.recording import recorder as _planted\n",
        "stray.py": "X = 1\n",
        "solvers/_planted.py": "import json\nfrom rigctl.sim import table\n",
        "sim/_planted.py": "from rigctl import cli\n",
        "drivers/_planted.py": "from rigctl.analysis import results\nfrom rigctl.commands import sync_cmd\n",
        "analysis/_planted.py": "from rigctl.report import report\n",
        "engine/engine.py": "from rigctl.analysis import sync as _planted\n",
    }
    r = lint(link_tree(tmp_path, planted))
    assert r.returncode != 0, r.stdout[-3000:]
    out = r.stdout
    for c in CONTRACTS.values():
        assert f"{c['name']} BROKEN" in out, (c["name"], out[-4000:])
    for line in ("rigctl.solvers._planted -> json", "rigctl.solvers._planted -> rigctl.sim.table",
                 "rigctl.sim._planted -> rigctl.cli", "rigctl.drivers._planted -> rigctl.analysis.results",
                 "rigctl.drivers._planted -> rigctl.commands.sync_cmd", "rigctl.analysis._planted -> rigctl.report.report",
                 "rigctl.engine.engine -> rigctl.analysis.sync", "rigctl.errors -> rigctl.recording.recorder",
                 "- rigctl.stray\n"):
        assert line in out, (line, out[-4000:])


def test_every_cli_module_is_protected() -> None:
    """The contract names every rigctl/commands/*_cmd.py (a new command module is covered only if listed)."""
    protected = sorted(m.removeprefix("rigctl.commands.") for m in CONTRACTS["cmd-only-from-cli"]["protected_modules"])
    assert protected == CMD_MODULES
    assert CONTRACTS["cmd-only-from-cli"]["allowed_importers"] == ["rigctl.cli"]


@pytest.mark.parametrize("name", [pytest.param(
    m, marks=pytest.mark.xfail(m in MOVING, strict=False,
                               reason="pipeline moving to rigctl.analysis"))
    for m in CMD_MODULES])
def test_cli_modules_stay_thin(name: str) -> None:
    """A *_cmd module parses, calls the application layer and prints: at most 200 lines."""
    n = len((ROOT / "rigctl" / "commands" / f"{name}.py").read_text().splitlines())
    assert n <= 200, f"rigctl/commands/{name}.py has {n} lines; move its logic into rigctl/analysis/"


def _command(*args: str) -> subprocess.CompletedProcess:
    """The developers' command of docs/architecture.md, run from the repository root."""
    return subprocess.run([sys.executable, "tests/lint_layers.py", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=300, env=dict(os.environ, COLUMNS="400"))


def test_the_documented_command_keeps_the_contracts() -> None:
    r = _command()
    assert r.returncode == 0, r.stdout[-6000:] + r.stderr[-3000:]
    assert f"{len(CONTRACTS)} kept, 0 broken" in r.stdout, r.stdout[-3000:]


def test_the_documented_command_fails_on_a_broken_import(tmp_path: Path) -> None:
    """A checkout whose drivers/ imports the application layer (and whose rigctl/ is this one):
    the command exits non-zero and prints the chain, so it sees drivers/ as rigctl.drivers."""
    repo = tmp_path / "repo"
    (repo / "drivers").mkdir(parents=True)
    for name in ("pyproject.toml", "rigctl", "sim"):
        (repo / name).symlink_to(ROOT / name)
    for p in (ROOT / "drivers").iterdir():
        if p.name != "__pycache__":
            (repo / "drivers" / p.name).symlink_to(p)
    (repo / "drivers" / "_planted.py").write_text("from rigctl.analysis import results\n")
    r = _command("--root", str(repo))
    assert r.returncode != 0, r.stdout[-3000:]
    assert f"{CONTRACTS['layers']['name']} BROKEN" in r.stdout, r.stdout[-4000:]
    assert "rigctl.drivers._planted -> rigctl.analysis.results" in r.stdout, r.stdout[-4000:]
