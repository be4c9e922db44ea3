"""The daemon over its Unix socket: owner-only access, malformed and oversized messages,
and a job submitted, paused, resumed and completed; then abort."""
from __future__ import annotations

import io
import json
import os
import re
import shutil
import signal
import socket
import stat
import subprocess
import tempfile
import time
from pathlib import Path

import h5py
import pytest

from rigctl.service import control
from rigctl.service.daemon import Daemon
from rigctl.run.runner import RunOptions
from rigctl.config.suspenders import SuspenderSettings

from helpers import derived_config, rigctl_cmd


@pytest.fixture
def daemon(tmp_path):
    cfg = derived_config(tmp_path, clock="scaled", speed=40.0)
    base = Path(tempfile.mkdtemp(prefix="rigctl-test-", dir="/tmp"))
    os.chmod(base, 0o755)  # traversable, so only the socket's own 0700 directory keeps others out
    sock = base / "ctl" / "rigctl.sock"
    d = Daemon(tmp_path / "runs", cfg, sock, console=io.StringIO(),
               options=RunOptions(suspenders=SuspenderSettings(hold_s=0.5, min_free_bytes=0)))
    d.start()
    assert control.wait_for_socket(sock, 10)
    try:
        yield d, sock
    finally:
        d.stop("test over")
        shutil.rmtree(base, ignore_errors=True)


def raw(sock, data: bytes) -> dict:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(10)
        s.connect(str(sock))
        try:
            s.sendall(data)
            s.shutdown(socket.SHUT_WR)
        except (BrokenPipeError, ConnectionResetError):
            pass
        out = b""
        while chunk := s.recv(65536):
            out += chunk
    return json.loads(out)


def test_socket_is_owner_only_and_rejects_bad_messages_without_harm(daemon):
    d, sock = daemon
    assert stat.S_IMODE(sock.stat().st_mode) == 0o600
    assert stat.S_IMODE(sock.parent.stat().st_mode) == 0o700
    big = b'{"v": 1, "cmd": "status", "args": {"x": "' + b"a" * (control.MAX_MESSAGE + 10) + b'"}}\n'
    bad = {
        big: "larger than",
        b"not json at all\n": "not JSON",
        b"[1, 2, 3]\n": "must be a JSON object",
        b'{"v": 1, "cmd": "format-disk"}\n': "unknown command",
        b'{"v": 2, "cmd": "status"}\n': "protocol version",
        b'{"v": 1, "cmd": "submit", "args": {}}\n': "missing argument 'procedure'",
        b'{"v": 1, "cmd": "submit", "args": {"procedure": 5}}\n': "must be str",
        b'{"v": 1, "cmd": "logs", "args": {"lines": -1}}\n': "lines must be",
        b'{"v": 1, "cmd": "status", "shell": "rm -rf /"}\n': "unknown request fields",
        b'{"v": 1, "cmd": "submit", "args": {"procedure": "relative.yaml"}}\n': "must be absolute",
        b"\xff\xfe\n": "not JSON",
    }
    for msg, why in bad.items():
        reply = raw(sock, msg)
        assert reply["ok"] is False and why in reply["error"], (msg[:60], reply)
    reply = control.request(sock, "status")  # still serving, unharmed
    assert reply["ok"] and reply["state"] == "idle" and reply["job"] is None


def _as_nobody(fn) -> tuple[int, str]:
    """Run fn() in a forked child with uid/gid 65534; its exit code and message."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # child
        os.close(r)
        try:
            os.setgid(65534)
            os.setuid(65534)
            msg = fn()
            code = 0
        except BaseException as exc:  # noqa: BLE001
            msg, code = f"{type(exc).__name__}: {exc}", 1
        os.write(w, msg.encode()[:4000])
        os._exit(code)
    os.close(w)
    out = b""
    while chunk := os.read(r, 4096):
        out += chunk
    os.close(r)
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status), out.decode()


def test_socket_refuses_a_client_that_is_not_its_owner(daemon):
    if os.geteuid() != 0:
        pytest.skip("needs root to run a client as another uid (nobody)")
    d, sock = daemon
    # 1) the filesystem keeps other users out: 0700 directory, 0600 socket
    code, msg = _as_nobody(lambda: json.dumps(control.request(sock, "status")))
    assert code == 1 and "PermissionError" in msg
    # 2) even if the permissions were loosened by mistake, SO_PEERCRED refuses the other uid
    os.chmod(sock.parent, 0o755)
    os.chmod(sock, 0o666)
    try:
        code, msg = _as_nobody(lambda: json.dumps(control.request(sock, "abort")))
    finally:
        os.chmod(sock.parent, 0o700)
        os.chmod(sock, 0o600)
    assert code == 0, msg
    reply = json.loads(msg)
    assert reply["ok"] is False and "not the daemon's owner" in reply["error"]
    assert control.request(sock, "status")["ok"]


# the warm-up is long enough (5 s of wall time at 40x) that `status --watch` can start, print three
# lines and the pause can land while the job still runs, on a fast idle machine too (with 40 s the
# job was sometimes done before the pause)
PROC = """procedure: daemon-job
steps:
  - warmup:
      duration: 200 s
  - orientations:
      angles_deg: [[0, 0, 0], [90, 0, 0]]
      sample: 20 s
      settle: {hold: 1 s, timeout: 60 s}
"""


def wait_state(sock, states, timeout=30.0) -> dict:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        st = control.request(sock, "status")
        if st["state"] in states:
            return st
        time.sleep(0.02)
    raise AssertionError(f"daemon never reached {states}: {st}")


def last_job_done(sock, timeout=60.0) -> dict:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        job = control.request(sock, "queue")["jobs"][-1]
        if job["state"] not in ("queued", "running"):
            return job
        time.sleep(0.02)
    raise AssertionError(f"job never finished: {job}")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_status_watch_ends_on_a_signal_even_when_started_with_sigint_ignored(daemon, sig):
    """CI starts the suite from a non-interactive shell's background job, so every process in it
    inherits SIGINT ignored; Python then installs no KeyboardInterrupt handler, and a watch loop
    that relied on one never ended on Ctrl-C (stop 24's CI: not within 20 s)."""
    d, sock = daemon
    watch = subprocess.Popen([*rigctl_cmd(), "status", "--watch", "--interval", "0.2", "--socket", str(sock)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        first = [watch.stdout.readline() for _ in range(2)]  # up and polling
        watch.send_signal(sig)
        out, err = watch.communicate(timeout=20)
    finally:
        if watch.poll() is None:
            watch.kill()
    assert watch.returncode == 0, err
    lines = ("".join(first) + out).splitlines()
    assert len(lines) >= 2 and all(re.match(r"^\d\d:\d\d:\d\dZ \| idle$", ln) for ln in lines), lines


def test_submit_pause_resume_complete_then_abort(daemon, tmp_path):
    d, sock = daemon
    proc = tmp_path / "job.yaml"
    proc.write_text(PROC)
    bad = tmp_path / "bad.yaml"
    bad.write_text("steps:\n  - rates:\n      axes: [z]\n      rates_dps: [9000]\n")
    reply = control.request(sock, "submit", {"procedure": str(bad)})
    assert not reply["ok"] and f"{bad}:4:" in reply["error"] and "limit" in reply["error"]
    assert control.request(sock, "submit", {"procedure": str(proc)})["ok"]
    wait_state(sock, ("running",))
    # `status --watch` as a user runs it: one plain progress line per interval until Ctrl-C
    watch = subprocess.Popen([*rigctl_cmd(), "status", "--watch", "--interval", "0.2", "--socket", str(sock)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    first = [watch.stdout.readline() for _ in range(3)]  # blocks until the client is up and polling
    watch.send_signal(signal.SIGINT)
    out, err = watch.communicate(timeout=20)
    assert watch.returncode == 0, err
    out = "".join(first) + out
    lines = out.splitlines()
    assert len(lines) >= 3, out
    steps = re.compile(r"^\d\d:\d\d:\d\dZ \| running \| job 1 job\.yaml \| \[[1-3]/3\] .* \| left ~")
    assert all(steps.match(ln) for ln in lines), out
    assert "\r" not in out and "\x1b" not in out  # plain lines, no bar
    assert control.request(sock, "pause")["ok"]
    st = wait_state(sock, ("paused",))
    assert st["suspenders"] == {"operator": "paused by operator (rigctl pause)"}
    time.sleep(0.3)
    assert control.request(sock, "status")["state"] == "paused"
    assert control.request(sock, "resume")["ok"]
    wait_state(sock, ("running",))
    job = last_job_done(sock)
    assert job["state"] == "complete", job
    rec = os.path.join(job["run_dir"], "recording.h5")
    with h5py.File(rec, "r") as f:
        assert f["run/status"][0] == b"complete"
        msgs = [m.decode() for m in f["events/message"][()]]
        assert any(m.startswith("running -> pausing: paused by operator") for m in msgs)
        assert any(m.startswith("paused -> running:") for m in msgs)
        assert [s for s in f["segments/status"][()] if s == b"complete"].__len__() == 3
    logs = control.request(sock, "logs", {"lines": 5})
    assert logs["ok"] and logs["lines"] and all(json.loads(line)["utc"] for line in logs["lines"])
    # abort: the table is stopped and the recording closed as interrupted
    assert control.request(sock, "submit", {"procedure": str(proc)})["ok"]
    wait_state(sock, ("running",))
    time.sleep(0.2)
    assert control.request(sock, "abort")["ok"]
    job = last_job_done(sock)
    assert job["state"] == "interrupted" and "abort requested" in job["message"]
    with h5py.File(os.path.join(job["run_dir"], "recording.h5"), "r") as f:
        assert f["run/status"][0] == b"interrupted"
        last = int(f["table/status"][-1])
        assert all(not (last >> (16 * a)) & 0x2 for a in range(3))  # servo off


def test_a_handler_error_keeps_its_exit_code_and_a_bug_its_traceback(tmp_path):
    """rigctl.errors through the socket: a refusal raised by the handler answers with its own
    line and exit code (2 for InputError, 1 for RunFailure); any other exception is a bug: the
    reply says so with exit code 1 and the daemon log gets the traceback."""
    from rigctl.errors import InputError, RunFailure

    def handler(cmd, args):
        if cmd == "status":
            raise InputError("no such thing", "p.yaml", 3)
        if cmd == "history":
            raise RunFailure("the disk is full")
        return {"ok": True, "n": 1 // 0}

    logged = []
    base = Path(tempfile.mkdtemp(prefix="rigctl-test-", dir="/tmp"))
    srv = control.ControlServer(base / "ctl" / "rigctl.sock", handler,
                                log=lambda kind, msg, **kw: logged.append((kind, msg, kw)))
    srv.start()
    try:
        r = control.request(srv.path, "status")
        assert r == {"ok": False, "error": "p.yaml:3: no such thing", "exit_code": 2}, r
        r = control.request(srv.path, "history")
        assert r == {"ok": False, "error": "the disk is full", "exit_code": 1}, r
        r = control.request(srv.path, "queue")
        assert r["ok"] is False and r["exit_code"] == 1 and r["error"].startswith("ZeroDivisionError"), r
        assert "traceback in the daemon log" in r["error"]
    finally:
        srv.close()
        shutil.rmtree(base, ignore_errors=True)
    bugs = [kw["traceback"] for kind, msg, kw in logged if kind == "error"]
    assert len(bugs) == 1 and "Traceback" in bugs[0] and "1 // 0" in bugs[0], logged
    assert not any("traceback" in kw for kind, msg, kw in logged if kind != "error")


def _serve_refused(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    """`rigctl serve ARGS` that must refuse to start: it exits within 30 s (a daemon that starts
    instead runs until the timeout kills it, and the test fails on that)."""
    cfg = derived_config(tmp_path, name="sim.yaml")
    try:
        return subprocess.run([*rigctl_cmd(), "serve", "--config", str(cfg), *args], capture_output=True,
                              text=True, timeout=30, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired as exc:
        pytest.fail(f"rigctl serve {' '.join(args)} started instead of refusing: {exc.stderr!r}")


def test_a_second_daemon_on_the_same_runs_directory_refuses_and_leaves_the_first_alone(daemon, tmp_path):
    """A second `rigctl serve` on the runs directory of a running one (another socket: another
    session's $XDG_RUNTIME_DIR) refuses, names the first's pid, and neither rewrites the first's
    job list nor writes in its log: before, it marked the first's running job 'crashed' and queued
    a resume of the same run directory, and with its own socket went on to run that resume."""
    d, sock = daemon
    state = tmp_path / "runs" / ".rigctl-daemon"
    jobs_before = (state / "jobs.json").read_bytes() if (state / "jobs.json").exists() else None
    log_before = (state / "daemon.log.jsonl").read_bytes()
    other = sock.parent.parent / "other.sock"
    r = _serve_refused(tmp_path, "--runs", str(tmp_path / "runs"), "--socket", str(other))
    assert r.returncode == 1, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "another rigctl serve" in lines[0] and f"pid {os.getpid()}" in lines[0], r.stderr
    assert "internal error" not in r.stderr and "Traceback" not in r.stderr
    assert not other.exists()
    assert ((state / "jobs.json").read_bytes() if (state / "jobs.json").exists() else None) == jobs_before
    assert (state / "daemon.log.jsonl").read_bytes() == log_before
    assert control.request(sock, "ping")["ok"]  # the first daemon still answers


def test_serve_on_a_socket_or_port_in_use_says_so_in_one_line(daemon, tmp_path):
    """`rigctl serve` on the socket of a running daemon, and `--http` on a port another program
    listens on: one line naming the socket / address and what to do, exit 1 -- before, each was an
    'internal error' (RuntimeError; for the port, from joining a thread never started)."""
    _d, sock = daemon
    r = _serve_refused(tmp_path, "--runs", str(tmp_path / "runs-b"), "--socket", str(sock))
    assert r.returncode == 1, r.stderr
    assert r.stderr.count("\n") == 1 and "already listens on this socket" in r.stderr and str(sock) in r.stderr, r.stderr
    assert "internal error" not in r.stderr

    pytest.importorskip("uvicorn")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        r = _serve_refused(tmp_path, "--runs", str(tmp_path / "runs-c"), "--socket", str(sock.parent.parent / "c.sock"),
                           "--http", f"127.0.0.1:{port}")
    assert r.returncode == 1, r.stderr
    assert r.stderr.count("\n") == 1 and f"--http 127.0.0.1:{port}" in r.stderr and "in use" in r.stderr, r.stderr
    assert "internal error" not in r.stderr
    # the refused daemon let go of its runs directory: a daemon can start there now
    again = Daemon(tmp_path / "runs-c", derived_config(tmp_path, name="sim.yaml"), sock.parent.parent / "d.sock",
                   console=io.StringIO())
    again._close("test over")


def test_status_starting_counts_from_when_the_job_was_taken(tmp_path):
    """`rigctl status` between taking a job and its first step says `starting since` the time
    the job was taken -- before, the time the daemon had gone idle (the daemon's start, or the
    end of the previous job hours ago), so a job just submitted looked stuck for hours."""
    base = Path(tempfile.mkdtemp(prefix="rigctl-test-", dir="/tmp"))
    d = Daemon(tmp_path / "runs", derived_config(tmp_path), base / "ctl" / "rigctl.sock", console=io.StringIO())
    try:
        idle_since = d.handle("status", {})["since_utc"]
        job = d._new_job("run", procedure=str(tmp_path / "p.yaml"))
        job.state, job.started_utc = "running", "2031-05-06T07:08:09.654321Z"  # taken by the worker
        d.current = job
        reply = d.handle("status", {})
        assert reply["state"] == "starting" and reply["since_utc"] == "2031-05-06T07:08:09Z" != idle_since
        d.server.start()  # what `rigctl status` prints of it
        r = subprocess.run([*rigctl_cmd(), "status", "--socket", str(base / "ctl" / "rigctl.sock")],
                           capture_output=True, text=True, timeout=60)
        assert "starting since 07:08:09Z" in r.stdout, r.stdout + r.stderr
    finally:
        d._close("test over")
        shutil.rmtree(base, ignore_errors=True)
