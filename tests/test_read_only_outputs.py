"""A recording on a read-only share (an archive mounted read-only, another user's run): the
commands that store their results in the recording (allan, calibrate, sync) or beside it
(report, an output file option) refuse it before any work, in one line that names the file, the
reason and what to do, exit 2 -- instead of an HDF5 "unable to open file ... errno = 30" after
the whole analysis (minutes on a long capture), exit 1.

The read-only place is real: a read-only bind mount when this process may mount (root), else a
directory and file without write permission (which root would ignore)."""
from __future__ import annotations

import contextlib
import io
import os
import shutil
import subprocess
from pathlib import Path

import h5py
import pytest

from helpers import ROOT

from rigctl import cli
from rigctl.config.config import load_config
from rigctl.engine.procedure import load_procedure
from rigctl.run.runner import run_procedure


@pytest.fixture
def read_only_run(tmp_path):
    """(a run directory holding a short emulated recording, read-only; the reason the commands
    must give)."""
    cfg = load_config(ROOT / "configs" / "sim.yaml")
    proc = load_procedure(ROOT / "procedures" / "warmup.yaml", {"warmup": "20 s"}, cfg.limits)
    res = run_procedure(proc, cfg, tmp_path / "runs", console=io.StringIO(), install_signals=False)
    src = Path(res.recording).parent
    ro = tmp_path / "ro"
    ro.mkdir()
    shutil.copytree(src, ro / "run")
    if os.geteuid() == 0:
        r = subprocess.run(["mount", "--bind", "-o", "ro", str(ro), str(ro)], capture_output=True, text=True)
        if r.returncode != 0 or os.access(ro / "run" / "recording.h5", os.W_OK):
            subprocess.run(["umount", "-l", str(ro)], capture_output=True)
            pytest.skip(f"a read-only bind mount is not permitted here: {r.stderr.strip()}")
        try:
            yield ro / "run", "read-only file system"
        finally:
            subprocess.run(["umount", "-l", str(ro)], capture_output=True)
    else:
        os.chmod(ro / "run" / "recording.h5", 0o444)
        os.chmod(ro / "run", 0o555)
        os.chmod(ro, 0o555)
        try:
            yield ro / "run", "no write permission"
        finally:
            os.chmod(ro, 0o755)
            os.chmod(ro / "run", 0o755)


def _main(*argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(list(argv))
    return code, out.getvalue(), err.getvalue()


def test_commands_refuse_a_read_only_recording_before_the_work(read_only_run, tmp_path):
    run, reason = read_only_run
    rec = run / "recording.h5"
    with h5py.File(rec, "r") as f:
        before = sorted(f.get("results", {}).keys())
    for cmd, group in (("allan", "allan"), ("calibrate", "calibration"), ("sync", "sync")):
        code, out, err = _main(cmd, str(rec), "--db", "none") if cmd != "sync" else _main(cmd, str(rec))
        lines = err.strip().splitlines()
        assert code == 2, (cmd, code, err)
        assert len(lines) == 1, (cmd, err)
        assert str(rec) in lines[0] and reason in lines[0] and f"/results/{group}" in lines[0], lines[0]
        assert "copy it to a writable directory" in lines[0], lines[0]
        assert "analysing" not in out, (cmd, out)  # refused before the analysis began
    code, _out, err = _main("report", str(run))
    assert code == 2 and err.count("\n") == 1 and str(run) in err and reason in err and "--out DIR" in err, err
    # an output file option in the read-only directory, the recording itself writable
    rec_rw = tmp_path / "rw.h5"
    shutil.copy(rec, rec_rw)
    os.chmod(rec_rw, 0o644)
    code, out, err = _main("allan", str(rec_rw), "--db", "none", "--json", str(run / "allan.json"))
    assert code == 2 and err.count("\n") == 1 and "--json" in err and reason in err, err
    assert "analysing" not in out
    with h5py.File(rec, "r") as f:
        assert sorted(f.get("results", {}).keys()) == before
    # rigctl run --out into the read-only directory: refused before the rig opens
    code, out, err = _main("run", str(ROOT / "procedures" / "warmup.yaml"), "-p", "warmup=5 s", "--out", str(run.parent))
    assert code == 2 and err.count("\n") == 1 and f"--out {run.parent}" in err and reason in err, err
    assert out == ""


def test_run_out_that_is_a_file_is_refused_before_the_rig_opens(tmp_path):
    """`rigctl run --out FILE` (or a path under a file): one line naming --out, exit 2, before
    the config line; before, 'failed: FILE: File exists' / 'Not a directory', exit 1."""
    f = tmp_path / "afile"
    f.write_text("")
    proc = str(ROOT / "procedures" / "warmup.yaml")
    for out_dir in (f, f / "sub"):
        code, out, err = _main("run", proc, "-p", "warmup=5 s", "--out", str(out_dir))
        assert code == 2 and err.count("\n") == 1 and f"--out {out_dir}" in err and "not a directory" in err, err
        assert out == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]
