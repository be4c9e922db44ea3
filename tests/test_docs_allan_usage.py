"""docs/allan.md "Using rigctl allan" stays true: every command of its sh block runs on an
emulated capture (procedures/allan-overnight.yaml's warm-up and capture, 2 min at 100 Hz), exits 0, and
writes what the section's table says: the console table's columns and units, the Kalibr keys,
the JSON keys and the CSV header."""
from __future__ import annotations

import csv
import json
import re
import shlex
from pathlib import Path

import pytest
import yaml

from helpers import ROOT, rigctl_in_process

DOC = (ROOT / "docs" / "allan.md").read_text(encoding="utf-8")
SECTION = DOC.split("## Using rigctl allan\n", 1)[1].split("\n## ", 1)[0]
COMMANDS = [ln for ln in re.search(r"```sh\n(.*?)```", SECTION, re.S).group(1).splitlines()
            if ln.startswith("rigctl allan ")]


@pytest.fixture(scope="module")
def rec(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("allan-docs")
    # allan-overnight.yaml's steps without its solve step (the analysis is what the commands do)
    proc = out / "capture.yaml"
    proc.write_text(f"procedure: allan-docs\nsteps:\n  - include: {ROOT / 'procedures' / 'warmup.yaml'}\n"
                    "  - capture: {duration: 2 min, label: overnight static}\n")
    r = rigctl_in_process("run", str(proc), "-p", "warmup=10 s", "--out", str(out / "runs"))
    assert r.returncode == 0, r.stderr[-2000:]
    (path,) = (out / "runs").glob("*/recording.h5")
    return path


def test_the_section_documents_every_output_option():
    assert len(COMMANDS) >= 3
    used = " ".join(COMMANDS)
    for opt in ("--kalibr", "--json", "--csv", "--plot", "--taus", "--axes"):
        assert opt in used, opt
        assert f"`{opt}" in SECTION, f"{opt} is not in the section's table"


@pytest.mark.parametrize("command", COMMANDS)
def test_documented_command_runs_and_writes_what_the_table_says(command: str, rec: Path, tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch):
    args = [a.replace("$REC", str(rec)) for a in shlex.split(command)][1:]
    # in this process (what the command computes and writes, not the process; a subprocess
    # spent ~4 s of CPU per command on the interpreter's imports), run from tmp_path as the
    # section's relative output names are
    monkeypatch.chdir(tmp_path)
    r = rigctl_in_process(*args, "--db", "none")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "Traceback" not in r.stderr
    axes = args[args.index("--axes") + 1].split(",") if "--axes" in args else ["gx", "gy", "gz", "ax", "ay", "az"]
    assert re.findall(r"^== (\w\w) ", r.stdout, re.M) == axes
    assert re.search(r"tau_s\s+adev_deg/h\s+lo68\s+hi68\s+alpha\s+edf", r.stdout)
    if "ax" in axes:
        assert re.search(r"tau_s\s+adev_mg\s+lo68\s+hi68\s+alpha\s+edf", r.stdout)
    assert "deg/sqrt(h) [" in r.stdout  # a resolved N with its 95 % interval, as the section reads it
    if "--plot" in args:
        assert (tmp_path / args[args.index("--plot") + 1]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    if "--kalibr" in args:
        k = yaml.safe_load((tmp_path / args[args.index("--kalibr") + 1]).read_text())
        keys = ("accelerometer_noise_density", "accelerometer_random_walk", "gyroscope_noise_density",
                "gyroscope_random_walk", "rostopic", "update_rate")
        assert set(keys) <= set(k) and all(f"`{key}`" in SECTION for key in keys)
    if "--json" in args:
        d = json.loads((tmp_path / args[args.index("--json") + 1]).read_text())
        gx = d["axes"]["gx"]
        for key in ("adev_rad/s", "adev_deg/h", "lo68_deg/h", "spikes", "tones", "warmup"):
            assert key in gx and f"`{key}" in SECTION, key
        co = gx["fit"]["coefficients"]
        assert "ci95" in co["N"] and "value" in co["N"]
        assert any("upper95" in co[t] for t in "QBKR")  # a 2-min capture leaves bounds
    if "--csv" in args:
        with open(tmp_path / args[args.index("--csv") + 1], newline="") as fh:
            header = next(csv.reader(fh))
        assert f"`{','.join(header)}`" in SECTION, header
