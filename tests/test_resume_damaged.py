"""`rigctl resume` on a cut-off run whose recording was damaged or hand-edited: every group and
dataset a resume reads or appends to deleted (h5py), the format attribute gone, /run/status
empty. Each is refused before anything is touched -- exit 2, one line on stderr naming the
recording, what is missing and what to do, no traceback, recording and checkpoint unchanged --
in process for every case and as real subprocesses for a few. A segment table left uneven by a
crash mid-flush is not damage: the resume trims it (as the reopen does) and completes."""
from __future__ import annotations

import contextlib
import io
import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest

from helpers import ROOT, make_cut_off, rigctl_cmd
from rigctl import cli
from rigctl.config.config import load_config
from rigctl.engine.procedure import load_procedure
from rigctl.recording.recorder import LAYOUT
from rigctl.run.runner import run_procedure

PROC = "procedure: resume-damaged\nsteps:\n  - warmup:\n      duration: 2 s\n  - capture:\n      duration: 2 s\n"
#: what a resume reads or appends to (groups always; pulses and chamber where the file has them)
REQUIRED_GROUPS = ("imu", "table", "segments", "events", "run", "meta")
HINT = "cannot be resumed"


def _damage() -> dict[str, tuple[Callable[[h5py.File], None], str]]:
    """name -> (edit of the open recording, what the refusal must name)."""
    out: dict[str, tuple[Callable[[h5py.File], None], str]] = {}
    for g in REQUIRED_GROUPS:
        out[f"group-{g}"] = (lambda f, g=g: f.__delitem__(g), f"/{g}")
    for g, ds in LAYOUT.items():
        for d in ds:
            out[f"{g}-{d}"] = (lambda f, g=g, d=d: f[g].__delitem__(d), f"/{g}/{d}")
    out["run-status"] = (lambda f: f["run"].__delitem__("status"), "/run/status")

    def empty_status(f: h5py.File) -> None:
        dt = f["run/status"].dtype
        del f["run/status"]
        f["run"].create_dataset("status", shape=(0,), dtype=dt)

    out["run-status-empty"] = (empty_status, "/run/status is empty")
    out["format-attribute"] = (lambda f: f.attrs.__delitem__("format"), "not a rigctl recording")
    return out


@pytest.fixture(scope="module")
def cut_off(tmp_path_factory) -> tuple[Path, Path]:
    """(runs directory, a run in it cut off during its capture: checkpoint after step 1)."""
    tmp = tmp_path_factory.mktemp("resume-damaged")
    cfg = load_config(ROOT / "configs" / "sim.yaml")
    proc_path = tmp / "p.yaml"
    proc_path.write_text(PROC)
    res = run_procedure(load_procedure(proc_path, limits=cfg.limits), cfg, tmp / "runs",
                        console=io.StringIO(), install_signals=False)
    assert res.status == "complete", res.message
    make_cut_off(res.run_dir, res.recording)
    return tmp / "runs", res.run_dir


def _copy(cut_off: tuple[Path, Path], name: str, edit: Callable[[h5py.File], None]) -> Path:
    runs, run = cut_off
    d = runs / name
    shutil.copytree(run, d)
    with h5py.File(d / "recording.h5", "r+") as f:
        edit(f)
    return d


def _resume_in_process(runs: Path, d: Path) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = cli.main(["resume", str(d), "--runs", str(runs), "--socket", str(runs / "none.sock")])
    return code, err.getvalue()


def _one_clear_line(code: int, err: str, rec: Path, what: str) -> None:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, err
    assert len(lines) == 1, err
    assert "Traceback" not in err and "internal error" not in err, err
    assert lines[0].startswith(f"rigctl resume: error: {rec}: "), err
    assert what in lines[0] and HINT in lines[0], err


def test_every_damaged_recording_is_refused_with_one_line(cut_off) -> None:
    runs = cut_off[0]
    cases = _damage()
    assert len(cases) > 40
    for name, (edit, what) in cases.items():
        d = _copy(cut_off, name, edit)
        rec = d / "recording.h5"
        before = (rec.read_bytes(), (d / "checkpoint.json").read_text())
        code, err = _resume_in_process(runs, d)
        _one_clear_line(code, err, rec, what)
        assert (rec.read_bytes(), (d / "checkpoint.json").read_text()) == before, name


def test_subprocess_refuses_with_the_same_line(cut_off) -> None:
    runs = cut_off[0]
    cases = _damage()
    for name in ("events-message", "segments-step", "group-meta"):
        edit, what = cases[name]
        d = _copy(cut_off, f"sub-{name}", edit)
        r = subprocess.run([*rigctl_cmd(), "resume", str(d), "--runs", str(runs),
                            "--socket", str(runs / "none.sock")],
                           capture_output=True, text=True, timeout=120, cwd=ROOT)
        _one_clear_line(r.returncode, r.stderr, d / "recording.h5", what)
        assert (r.returncode, r.stderr) == _resume_in_process(runs, d), name


def test_uneven_segment_table_of_a_crash_mid_flush_resumes(cut_off) -> None:
    """A crash while the second segment row was appended: its first columns (kind ... t_start)
    have two rows, the rest one. The resume reads the one whole row (the warm-up, complete),
    redoes the capture and completes."""
    def mid_flush(f: h5py.File) -> None:
        for k in ("kind", "label", "step", "first_sample", "last_sample", "t_start"):
            f["segments"][k].resize(2, axis=0)

    runs = cut_off[0]
    d = _copy(cut_off, "uneven", mid_flush)
    code, err = _resume_in_process(runs, d)
    assert code == 0, err
    with h5py.File(d / "recording.h5", "r") as f:
        assert len({f["segments"][k].shape[0] for k in LAYOUT["segments"]}) == 1
        kinds = f["segments/kind"][()][f["segments/status"][()] == b"complete"]
        assert sorted(kinds.tolist()) == [b"capture", b"warmup"]
        assert f["run/status"][0] == b"complete"
        assert np.all(np.diff(f["imu/time"][()]) > 0)


def _file_damage() -> dict[str, tuple[Callable[[Path], None], str]]:
    """name -> (what is done to the run's recording.h5 as a file, what the refusal must say):
    files h5py cannot open at all, or that are damaged under their superblock."""
    def cut(n: Callable[[int], int]) -> Callable[[Path], None]:
        return lambda p: p.write_bytes(p.read_bytes()[:n(p.stat().st_size)])

    def directory(p: Path) -> None:
        p.unlink()
        p.mkdir()

    def garbage(p: Path) -> None:      # the superblock kept, 4 KiB after it overwritten
        b = bytearray(p.read_bytes())
        b[2048:2048 + 4096] = b"\xff" * 4096
        p.write_bytes(bytes(b))
    return {"text": (lambda p: p.write_text("not a recording\n"), "not an HDF5 file"),
            "empty": (lambda p: p.write_bytes(b""), "empty file"),
            "truncated-1000": (cut(lambda n: 1000), "cut off: 1000 bytes"),
            "truncated-half": (cut(lambda n: n // 2), "cut off:"),
            "directory": (directory, "is a directory"),
            "garbage-inside": (garbage, "cannot be read as HDF5")}


def test_a_recording_hdf5_cannot_open_is_refused_with_one_line(cut_off) -> None:
    """Before: 'internal error: ValueError: ... not an HDF5 file' (text, empty; exit 1),
    'failed: ...: Is a directory' (exit 1); a truncated file hung the resume (a SWMR reader
    skips HDF5's own size check: the next test). Now each: exit 2, one line naming the recording, what is wrong
    and what to do; the checkpoint unchanged."""
    runs = cut_off[0]
    for name, (edit, what) in _file_damage().items():
        if name.startswith("truncated"):   # hung in process before: as subprocesses, below
            continue
        d = runs / f"file-{name}"
        shutil.copytree(cut_off[1], d)
        edit(d / "recording.h5")
        before = (d / "checkpoint.json").read_text()
        code, err = _resume_in_process(runs, d)
        _one_clear_line(code, err, d / "recording.h5", what)
        assert (d / "checkpoint.json").read_text() == before, name


def test_a_truncated_recording_does_not_hang_the_resume(cut_off) -> None:
    """Cut to 1000 bytes, or to half: as real subprocesses, with a limit (before, the resume
    hung: killed at the limit here)."""
    runs = cut_off[0]
    for name in ("truncated-1000", "truncated-half"):
        d = runs / f"sub-{name}"
        shutil.copytree(cut_off[1], d)
        edit, what = _file_damage()[name]
        edit(d / "recording.h5")
        r = subprocess.run([*rigctl_cmd(), "resume", str(d), "--runs", str(runs), "--socket",
                            str(runs / "none.sock")], capture_output=True, text=True, timeout=60, cwd=ROOT)
        _one_clear_line(r.returncode, r.stderr, d / "recording.h5", what)
