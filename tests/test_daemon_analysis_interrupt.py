"""SIGTERM and SIGINT to `rigctl serve` while a job analyses its complete recording.

Before: the daemon ran its jobs in a thread its signal handlers could not reach. A SIGTERM during
a job's analysis waited up to 30 s for the worker thread, then the process exited: when the
analysis had ended meanwhile the job said `complete`; when not, the interpreter's exit cut the
analysis wherever it was (a report half-made, the recording open for its results) and the job
stayed `running` in jobs.json with nothing in the log saying so; meanwhile `status` and the page
called the analysis "starting: opening the rig". Now the daemon runs its jobs in the main thread:
the signal stops the analysis as it stops `rigctl run`'s (every result whole or absent), the job
ends `interrupted` with analysis `interrupted` and one log line naming the command that redoes
it, the daemon exits 0 at once, a restart leaves the job as it is (an interrupted job is not
resumed by itself), and `POST /api/resume {"run": ID}` queues the analysis alone.
"""
from __future__ import annotations

import json
import signal
import time
import urllib.error
import urllib.request
from pathlib import Path

import h5py
import pytest

from helpers import ROOT, SHORT_ALLAN_PROCEDURE, allan_whole_or_absent, rigctl_cmd, start_process, stop_process
from hil_support import wait_until

pytest.importorskip("starlette")


class Served:
    """`rigctl serve --http` as a process, its log, and its HTTP API."""

    def __init__(self, base: Path, name: str) -> None:
        self.runs = base / "runs"
        self.log = base / f"{name}.log"
        self.proc, text = start_process(
            [*rigctl_cmd(), "serve", "--config", str(ROOT / "configs" / "sim.yaml"), "--runs", str(self.runs),
             "--socket", str(base / "s.sock"), "--http", "127.0.0.1:0", "--procedures", str(base / "procedures")],
            self.log, r"rigctl daemon: socket")  # after the line naming the API's address
        self.url = text.split("API at ")[1].split()[0].rstrip("/")
        self.token = (self.runs / ".rigctl-daemon" / "http-token").read_text().strip()

    def api(self, path: str, body: dict | None = None) -> dict:
        req = urllib.request.Request(self.url + path, method="GET" if body is None else "POST",
                                     data=None if body is None else json.dumps(body).encode(),
                                     headers={"Authorization": f"Bearer {self.token}"})
        try:
            with urllib.request.urlopen(req, timeout=20) as r:
                return json.loads(r.read())
        except urllib.error.HTTPError as exc:
            return {"http": exc.code, **json.loads(exc.read())}

    def lines(self) -> list[str]:
        return self.log.read_text().splitlines()

    def signal_in_analysis(self, signum: int, after: int = 0) -> float:
        """Once the log has an ``analysis:`` line past line ``after`` (the job's solvers start),
        check that the status says so, send ``signum``; the wall seconds until the job's end is
        logged (its state is saved just before). The process exits 0 after that, once the
        interpreter's final garbage collection is done (2-5 s at load 12-22: not timed here)."""
        wait_until(lambda: any(ln.startswith("analysis: ") for ln in self.lines()[after:]), 120,
                   "the job's analysis to start", poll=0.01)
        st = self.api("/api/status")
        jid = st["job"]["id"]
        assert st["state"] == "analysing" and st["reason"].startswith(f"job {jid}: analysing"), st
        t0 = time.monotonic()
        self.proc.send_signal(signum)
        wait_until(lambda: any(ln.startswith(f"job {jid} ") for ln in self.lines()[after:])
                   or self.proc.poll() is not None, 60, "the job's end", poll=0.01)
        took = time.monotonic() - t0
        assert self.proc.wait(timeout=60) == 0, self.log.read_text()[-3000:]
        return took


def _jobs(runs: Path) -> dict[int, dict]:
    return {j["id"]: j for j in json.loads((runs / ".rigctl-daemon" / "jobs.json").read_text())}


def _nothing_half_written(runs: Path, run_dir: Path) -> None:
    rec = run_dir / "recording.h5"
    with h5py.File(rec, "r") as f:  # a plain open: closed whole, no write flag left
        assert f["run/status"][0] == b"complete"
        assert set(f["segments/status"][()]) == {b"complete"}
    assert not [p for p in runs.rglob("*") if ".tmp" in p.name]
    allan_whole_or_absent(rec)
    if (run_dir / "report.html").exists():
        assert (run_dir / "report.html").read_text().rstrip().endswith("</html>")


def test_signals_during_a_jobs_analysis_end_it_interrupted_and_resumable(sock_dir):
    base = sock_dir
    (base / "procedures").mkdir()
    (base / "procedures" / "short-allan.yaml").write_text(SHORT_ALLAN_PROCEDURE)
    runs = base / "runs"

    # -- SIGTERM while job 1 analyses -----------------------------------------------------------
    d = Served(base, "serve1")
    try:
        assert d.api("/api/queue", {"procedure": "short-allan.yaml"})["job"] == 1
        took = d.signal_in_analysis(signal.SIGTERM)
    finally:
        stop_process(d.proc)
    assert took < 10, took  # before: 30 s (the worker thread's join), or the analysis' whole length
    job = _jobs(runs)[1]
    run_dir = Path(job["run_dir"])
    rec = run_dir / "recording.h5"
    redo = f"rigctl resume {run_dir} --runs {runs}"
    said = (f"analysis interrupted by SIGTERM: the recording {rec} is complete and closed, no result is "
            f"half-written ({redo} redoes the analysis)")
    assert (job["state"], job["analysis"], job["message"]) == ("interrupted", "interrupted", said)
    lines = d.lines()
    assert [ln for ln in lines if ln.startswith("job 1 ")] == [f"job 1 interrupted: {said}"]
    assert lines[-1] == "rigctl daemon stopped (daemon stopped by SIGTERM)"
    assert "Traceback" not in d.log.read_text()
    ck = json.loads((run_dir / "checkpoint.json").read_text())
    assert (ck["status"], ck["analysis"]) == ("complete", "interrupted")
    _nothing_half_written(runs, run_dir)

    # -- a new daemon: the job stays interrupted; the API resumes its analysis; SIGINT -----------
    d = Served(base, "serve2")
    try:
        q = d.api("/api/queue")
        assert q["queued"] == [] and [j["id"] for j in q["jobs"]] == [1]   # not resumed by itself
        assert d.api("/api/status")["state"] == "idle"
        (run,) = d.api("/api/runs")["runs"]
        assert (run["id"], run["status"], run["analysis"], run["job_state"]) == \
            (run_dir.name, "complete", "interrupted", "interrupted")
        after = len(d.lines())  # before the request: the job may start its analysis before it returns
        assert d.api("/api/resume", {"run": run_dir.name})["job"] == 2
        took = d.signal_in_analysis(signal.SIGINT, after)
    finally:
        stop_process(d.proc)
    assert took < 10, took
    lines = d.lines()
    # the resume ran the analysis only: the rig was not opened, no step ran
    assert any(ln.startswith(f"resuming {run_dir.name}: the run is complete, its analysis interrupted")
               for ln in lines)
    assert not any("started:" in ln for ln in lines)
    job = _jobs(runs)[2]
    said = said.replace("SIGTERM", "SIGINT")
    assert (job["kind"], job["state"], job["analysis"], job["message"]) == ("resume", "interrupted", "interrupted", said)
    assert [ln for ln in lines if ln.startswith("job 2 ")] == [f"job 2 interrupted: {said}"]
    assert lines[-1] == "rigctl daemon stopped (daemon stopped by SIGINT)"
    assert "Traceback" not in d.log.read_text()
    _nothing_half_written(runs, run_dir)
    assert json.loads((run_dir / "checkpoint.json").read_text())["analysis"] == "interrupted"
