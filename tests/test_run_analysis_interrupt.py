"""SIGTERM while ``rigctl run`` analyses a complete recording (its ``solve:`` step).

Before: the runner gave SIGINT/SIGTERM back to Python once the recording was closed, so a SIGTERM
during the solvers killed the process at once (exit -15, nothing on stderr, the checkpoint saying
"complete" and ``rigctl resume`` refusing: "nothing to resume"), and a kill in the middle of a
results write could leave it half-written. Now the signal stops the analysis (every results write
whole or not at all, rigctl.recording.shield), one line on stderr names the command that redoes
it, exit 130; that command (``rigctl resume RUN``) runs the analysis only.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
from pathlib import Path

import h5py
import numpy as np
import pytest

from helpers import ROOT, SHORT_ALLAN_PROCEDURE, allan_whole_or_absent, rigctl_cmd, rigctl_in_process

PROCEDURE = SHORT_ALLAN_PROCEDURE
CAPTURE_SAMPLES = 120 * 100  # 2 min at configs/sim.yaml's 100 Hz


def _rigctl(args: list[str], tmp_path: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1", RIGCTL_SOCKET=str(tmp_path / "no-daemon.sock"))
    return subprocess.Popen([*rigctl_cmd(), *args], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


def _terminate_at(proc: subprocess.Popen, prefix: str) -> tuple[list[str], str, bool]:
    """Read ``proc``'s stdout; SIGTERM it as soon as a line starts with ``prefix`` (from the
    reading thread: no polling delay). (stdout lines, stderr, whether the signal was sent)."""
    lines: list[str] = []
    sent = threading.Event()

    def read() -> None:
        for line in proc.stdout:
            lines.append(line.rstrip("\n"))
            if line.startswith(prefix) and not sent.is_set():
                proc.send_signal(signal.SIGTERM)
                sent.set()

    t = threading.Thread(target=read, daemon=True)
    t.start()
    try:
        proc.wait(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
    t.join(timeout=10)
    return lines, proc.stderr.read(), sent.is_set()


def test_sigterm_during_the_analysis_keeps_the_recording_and_says_how_to_redo_it(tmp_path, monkeypatch):
    (tmp_path / "proc.yaml").write_text(PROCEDURE)
    runs = tmp_path / "runs"
    proc = _rigctl(["run", str(tmp_path / "proc.yaml"), "--out", str(runs)], tmp_path)
    lines, err, sent = _terminate_at(proc, "analysis: ")
    out = "\n".join(lines)
    assert sent, out + err  # the run announced its analysis (the hook of this test)
    assert proc.returncode == 130, out + err
    assert "Traceback" not in out + err
    (run_dir,) = runs.iterdir()
    rec = run_dir / "recording.h5"
    err_lines = err.splitlines()
    redo = f"rigctl resume {run_dir} --runs {runs}"
    assert len(err_lines) == 1, err
    assert err_lines[0] == (f"rigctl run: interrupted: analysis interrupted by SIGTERM: the recording {rec} "
                            f"is complete and closed, no result is half-written ({redo} redoes the analysis)")

    # the recording: complete, readable with plain h5py, every sample of the capture in it
    with h5py.File(rec, "r") as f:
        assert f["run/status"][0] == b"complete"
        assert set(f["segments/status"][()]) == {b"complete"}
        kinds = list(f["segments/kind"][()])
        first, last = (f["segments"][k][()] for k in ("first_sample", "last_sample"))
        i = kinds.index(b"capture")
        assert last[i] - first[i] == CAPTURE_SAMPLES
        assert np.all(np.diff(f["imu/counter"][()].astype(np.int64)) == 1)
    # nothing half-written: no temporary file left, the Allan results whole or absent, the
    # report whole or absent, the results database without a row for an absent result
    assert not [p for p in runs.rglob("*") if ".tmp" in p.name]
    stored = allan_whole_or_absent(rec)
    if (run_dir / "report.html").exists():
        assert (run_dir / "report.html").read_text().rstrip().endswith("</html>")
    if not stored and (runs / "results.sqlite").exists():
        import sqlite3
        with sqlite3.connect(runs / "results.sqlite") as db:
            n = db.execute("select count(*) from analyses where recording = ?", (str(rec),)).fetchone()[0]
        assert n == 0
    ckpt = json.loads((run_dir / "checkpoint.json").read_text())
    assert (ckpt["status"], ckpt["analysis"]) == ("complete", "interrupted")
    events = [json.loads(ln) for ln in (run_dir / "run.log.jsonl").read_text().splitlines()]
    assert events[-1]["kind"] == "info" and events[-1]["message"] == f"recording: {rec}"

    # the command the line names redoes the analysis only (the rig is not opened again); it and
    # the second resume run through rigctl.cli.main in this process (helpers.rigctl_in_process):
    # what they write and say is tested here, the signal's process above
    assert redo.startswith("rigctl ")
    monkeypatch.setenv("RIGCTL_SOCKET", str(tmp_path / "no-daemon.sock"))
    r = rigctl_in_process(*redo.split()[1:])
    assert r.returncode == 0, r.stdout + r.stderr
    assert "Traceback" not in r.stdout + r.stderr and "started:" not in r.stdout
    assert allan_whole_or_absent(rec)
    assert (run_dir / "report.html").read_text().rstrip().endswith("</html>")
    with h5py.File(rec, "r") as f:
        assert f["run/status"][0] == b"complete" and f["imu/time"].shape[0] == len(f["imu/counter"])
    assert json.loads((run_dir / "checkpoint.json").read_text())["analysis"] == "done"
    # done: a second resume has nothing to do
    r = rigctl_in_process(*redo.split()[1:])
    assert r.returncode == 2 and "already complete; nothing to resume" in r.stderr, r.stderr


def test_a_results_write_is_whole_when_a_signal_arrives_in_its_middle(tmp_path):
    """rigctl.recording.shield: the runner's handler raises through shield.interrupt; a signal
    that arrives while write_results runs is raised once the group is whole."""
    from rigctl.recording import shield
    from rigctl.recording.recorder import write_results

    rec = tmp_path / "r.h5"
    with h5py.File(rec, "w") as f:
        f.create_dataset("x", data=np.arange(3))

    class SignalsWhenRead:  # an array whose conversion raises SIGTERM: the write's middle
        def __array__(self, dtype=None, copy=None):
            signal.raise_signal(signal.SIGTERM)
            return np.arange(5.0)

    class Stop(BaseException):
        pass

    old = signal.signal(signal.SIGTERM, lambda *_: shield.interrupt(Stop()))
    try:
        with pytest.raises(Stop):
            write_results(rec, "demo", {"a": 1}, {"first": (np.ones(2), "1"), "middle": (SignalsWhenRead(), "s"),
                                                  "last": (np.zeros(4), "m")})
        with pytest.raises(Stop):  # outside a write: at once
            signal.raise_signal(signal.SIGTERM)
    finally:
        signal.signal(signal.SIGTERM, old)
    with h5py.File(rec, "r") as f:
        g = f["results/demo"]
        assert json.loads(g.attrs["json"]) == {"a": 1}
        assert {k: g[k].attrs["units"] for k in g} == {"first": "1", "middle": "s", "last": "m"}
        np.testing.assert_array_equal(g["last"][()], np.zeros(4))
