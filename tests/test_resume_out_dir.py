"""`rigctl resume RUN` of a run made with `rigctl run --out DIR`, from a folder with no ./runs:
README gives the command as `rigctl resume RUN`, and RUN's own folder is where the run was
made; it refused ("... is not a run directory inside <cwd>/runs ... pass --runs DIR")."""
from __future__ import annotations

import contextlib
import io
from pathlib import Path

import h5py
import pytest

from helpers import ROOT, make_cut_off
from rigctl import cli
from rigctl.config.config import load_config
from rigctl.engine.procedure import load_procedure
from rigctl.run.runner import run_procedure

PROC = "procedure: resume-out\nsteps:\n  - warmup:\n      duration: 2 s\n  - capture:\n      duration: 2 s\n"


def _resume(argv: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = cli.main(argv)
    return code, err.getvalue()


def test_resume_finds_the_runs_folder_from_the_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = load_config(ROOT / "configs" / "sim.yaml")
    (tmp_path / "p.yaml").write_text(PROC)
    res = run_procedure(load_procedure(tmp_path / "p.yaml", limits=cfg.limits), cfg, tmp_path / "lab-runs",
                        console=io.StringIO(), install_signals=False)
    assert res.status == "complete", res.message
    make_cut_off(res.run_dir, res.recording)
    work = tmp_path / "elsewhere"
    work.mkdir()
    monkeypatch.chdir(work)  # no ./runs here
    code, err = _resume(["resume", str(res.run_dir), "--socket", str(tmp_path / "none.sock")])
    assert code == 0, err
    with h5py.File(res.recording, "r") as f:
        assert f["run/status"][0] == b"complete"
        assert len(f["segments/kind"]) == 2
    # --runs given and wrong: still refused with one line naming the run
    make_cut_off(res.run_dir, res.recording)
    code, err = _resume(["resume", str(res.run_dir), "--runs", str(work), "--socket", str(tmp_path / "none.sock")])
    assert code == 2 and f"{res.run_dir} is not a run directory inside {work}" in err, err
