"""One writer per run: `rigctl resume RUN` while another process still runs or resumes RUN
(a second terminal, the same command typed twice) is refused in one line naming that process,
exit 1, the recording untouched. Before, both resumes wrote a session into the same recording:
seen on the emulator, 27 segments for 26 steps, the last step twice, /imu/time going back at 5
places, and the file marked complete.

The holder here is another process holding the run's lock file (an exclusive flock on
RUN/.rigctl-run.lock, the protocol docs/daemon.md describes), as a running `rigctl run` or
`rigctl resume` holds it; once it exits the same resume goes through."""
from __future__ import annotations

import contextlib
import hashlib
import io
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np

from helpers import ROOT, make_cut_off
from rigctl import cli
from rigctl.config.config import load_config
from rigctl.engine.procedure import load_procedure
from rigctl.run.runner import run_procedure

PROC = "procedure: one-writer\nsteps:\n  - warmup:\n      duration: 2 s\n  - capture:\n      duration: 2 s\n"
HOLDER = """import fcntl, os, sys
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT, 0o600)
fcntl.flock(fd, fcntl.LOCK_EX)
os.ftruncate(fd, 0); os.write(fd, f"{os.getpid()}\\n".encode())
print("held", flush=True)
sys.stdin.read()
"""


def _resume(run_dir: Path, sock: Path) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = cli.main(["resume", str(run_dir), "--socket", str(sock)])
    return code, err.getvalue()


def test_a_second_writer_of_a_run_is_refused(tmp_path: Path) -> None:
    cfg = load_config(ROOT / "configs" / "sim.yaml")
    (tmp_path / "p.yaml").write_text(PROC)
    res = run_procedure(load_procedure(tmp_path / "p.yaml", limits=cfg.limits), cfg, tmp_path / "runs",
                        console=io.StringIO(), install_signals=False)
    assert res.status == "complete", res.message
    make_cut_off(res.run_dir, res.recording)
    before = hashlib.sha256(res.recording.read_bytes()).hexdigest()
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(res.run_dir / ".rigctl-run.lock")],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        code, err = _resume(res.run_dir, tmp_path / "none.sock")
        lines = err.strip().splitlines()
        assert code == 1, err
        assert len(lines) == 1 and str(res.run_dir) in lines[0] and f"pid {holder.pid}" in lines[0], err
        assert hashlib.sha256(res.recording.read_bytes()).hexdigest() == before
    finally:
        holder.stdin.close()
        holder.wait(timeout=30)
    code, err = _resume(res.run_dir, tmp_path / "none.sock")  # the holder gone: resumed once
    assert code == 0, err
    with h5py.File(res.recording, "r") as f:
        assert f["run/status"][0] == b"complete"
        assert len(f["segments/kind"]) == 2
        assert np.all(np.diff(f["imu/time"][()]) > 0)
