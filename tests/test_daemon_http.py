"""The daemon's HTTP API (rigctl/service/web.py) on a real uvicorn server on loopback, against the
daemon running the emulated rig: token rules, queue operations, a 24-position job to
`complete` with its report, oversized requests; and the live feed's bin means against numpy."""
from __future__ import annotations

import http.client
import io
import json
import os
import re
import shutil
import socket
import stat
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("starlette")
pytest.importorskip("uvicorn")

from rigctl.service import control  # noqa: E402
from rigctl.service.daemon import Daemon  # noqa: E402
from rigctl.service.livefeed import LiveFeed  # noqa: E402
from rigctl.run.runner import RunOptions  # noqa: E402
from rigctl.config.suspenders import SuspenderSettings  # noqa: E402
from rigctl.service.web import MAX_BODY, WebApi, WebServer  # noqa: E402

from helpers import ROOT, derived_config  # noqa: E402


class Client:
    """A small HTTP client on urllib: (status, JSON body or text)."""

    def __init__(self, base: str, token: str | None = None) -> None:
        self.base, self.token = base.rstrip("/"), token

    def __call__(self, method: str, path: str, body=None, token: str | None | bool = True):
        headers = {"Content-Type": "application/json"}
        tok = self.token if token is True else token
        if tok:
            headers["Authorization"] = f"Bearer {tok}"
        data = json.dumps(body).encode() if body is not None else None
        req = urllib.request.Request(self.base + path, data=data, method=method, headers=headers)
        try:
            with urllib.request.urlopen(req, timeout=30) as r:
                status, raw, ctype = r.status, r.read(), r.headers.get("content-type", "")
        except urllib.error.HTTPError as e:
            status, raw, ctype = e.code, e.read(), e.headers.get("content-type", "")
        return status, (json.loads(raw) if "json" in ctype else raw.decode())


@pytest.fixture
def daemon(tmp_path):
    cfg = derived_config(tmp_path)  # the emulated rig in virtual time: a procedure takes seconds
    base = Path(tempfile.mkdtemp(prefix="rigctl-http-", dir="/tmp"))
    d = Daemon(tmp_path / "runs", cfg, base / "ctl" / "rigctl.sock", console=io.StringIO(),
               options=RunOptions(suspenders=SuspenderSettings(hold_s=0.5, min_free_bytes=0)))
    d.start()
    web = d.start_http("127.0.0.1", 0, procedures_dir=ROOT / "procedures")
    token = (d.runs_dir / ".rigctl-daemon" / "http-token").read_text().strip()
    try:
        yield d, web, token
    finally:
        d.stop("test over")
        shutil.rmtree(base, ignore_errors=True)


def wait_job(api: Client, jid: int, timeout: float = 90.0) -> dict:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        _, q = api("GET", "/api/queue")
        job = next(j for j in q["jobs"] if j["id"] == jid)
        if job["state"] not in ("queued", "running"):
            return job
        time.sleep(0.1)
    raise AssertionError(f"job {jid} did not finish: {job}")


SHORT = {"warmup": "20 s", "sample": "3 s"}


def test_token_queue_operations_and_a_24pos_job_with_its_report(daemon):
    d, web, token = daemon
    tok_file = d.runs_dir / ".rigctl-daemon" / "http-token"
    assert stat.S_IMODE(tok_file.stat().st_mode) == 0o600 and len(token) >= 40
    assert web.sock.getsockname()[0] == "127.0.0.1"
    api = Client(web.url, token)

    # no token, a wrong token: nothing readable, nothing changes
    for bad in (None, "x" * len(token), token[:-1]):
        st, body = api("GET", "/api/status", token=bad)
        assert st == 401 and body["ok"] is False and "token" in body["error"]
        st, body = api("POST", "/api/queue", {"procedure": "24pos.yaml", "params": SHORT}, token=bad)
        assert st == 401
    st, q = api("GET", "/api/queue")
    assert st == 200 and q["jobs"] == [] and q["queued"] == []
    st, s = api("GET", "/api/status")
    assert st == 200 and s["state"] == "idle" and s["job"] is None

    # queue operations with the queue stopped (nothing starts meanwhile)
    assert api("POST", "/api/queue/stop")[1]["queue_running"] is False
    ids = []
    for n in range(3):
        st, r = api("POST", "/api/queue", {"procedure": "24pos.yaml", "params": {**SHORT, "discard": f"{n + 1} s"}})
        assert st == 200 and r["ok"], r
        ids.append(r["job"])
    st, r = api("POST", "/api/queue", {"procedure": "24pos.yaml", "params": {**SHORT, "discard": "2 s"}})
    assert st == 400 and f"job {ids[1]}" in r["error"] and "same" in r["error"]  # a duplicate
    st, r = api("POST", "/api/queue", {"procedure": "warmup.yaml", "params": {"warmup": "5 s"}, "position": 0})
    assert st == 200 and r["position"] == 1
    first = r["job"]
    assert api("GET", "/api/queue")[1]["queued"] == [first, *ids]
    assert api("POST", f"/api/queue/{first}/move", {"position": 2})[1]["queued"] == [ids[0], ids[1], first, ids[2]]
    st, r = api("DELETE", f"/api/queue/{ids[1]}")
    assert st == 200 and r["queued"] == [ids[0], first, ids[2]]
    assert api("DELETE", f"/api/queue/{ids[1]}")[0] == 400  # not queued any more
    for path, body in (("/api/queue", {"procedure": "../../etc/passwd"}), ("/api/queue", {"procedure": "/etc/x.yaml"}),
                       ("/api/queue", {"procedure": "24pos.yaml", "params": {"warmup": "2 weeks"}})):
        st, r = api("POST", path, body)
        assert st == 400 and not r["ok"], (body, r)
    st, r = api("POST", "/api/queue/clear")
    assert st == 200 and sorted(r["removed"]) == sorted([ids[0], first, ids[2]])
    _, h = api("GET", "/api/history")
    assert {j["id"]: j["state"] for j in h["jobs"]} == {i: "removed" for i in (*ids, first)}
    assert api("GET", "/api/queue")[1]["queued"] == []

    # a 24-position job through the API, to complete; the queue started again
    st, r = api("POST", "/api/queue", {"procedure": "24pos.yaml", "params": SHORT})
    assert st == 200
    jid = r["job"]
    time.sleep(0.3)
    assert api("GET", "/api/status")[1]["job"] is None  # the queue is stopped
    assert api("POST", "/api/queue/start")[1]["queue_running"] is True
    job = wait_job(api, jid)
    assert job["state"] == "complete", job
    st, runs = api("GET", "/api/runs")
    run = next(r for r in runs["runs"] if r.get("job") == jid)
    assert run["status"] == "complete" and run["procedure"] == "24pos.yaml" and run["id"] == Path(job["run_dir"]).name
    st, html = api("GET", run["report"])
    assert st == 200 and "<html" in html.lower() and "24pos" in html
    assert (Path(job["run_dir"]) / "report.html").is_file()
    assert api("GET", run["report"], token=None)[0] == 401
    # a ticket opens that report (and only that one) without the token
    st, t = api("POST", f"/api/runs/{run['id']}/ticket")
    assert st == 200 and t["url"].startswith(f"/api/runs/{run['id']}/report?ticket=")
    assert api("GET", t["url"], token=None)[0] == 200
    assert api("GET", t["url"].replace("ticket=", "ticket=x"), token=None)[0] == 401
    assert api("GET", "/api/runs/..%2F..%2Fetc/report")[0] == 404
    _, h = api("GET", "/api/history?limit=1")
    assert [j["id"] for j in h["jobs"]] == [jid] and h["jobs"][0]["state"] == "complete"

    # the Unix socket sees the same queue (one set of handlers)
    assert control.request(d.socket_path, "history", {"limit": 1})["jobs"][0]["id"] == jid


def _raw_http(port: int, head: bytes, body_chunks=(), read_first: bool = False) -> bytes:
    """Send a request by hand; the reply bytes (the server may close while we still send)."""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(head)
        if read_first:
            return s.recv(65536)
        try:
            for chunk in body_chunks:
                s.sendall(chunk)
        except (BrokenPipeError, ConnectionResetError):
            pass
        out = b""
        try:
            while chunk := s.recv(65536):
                out += chunk
                if b"\r\n\r\n" in out:
                    break
        except ConnectionResetError:
            pass
        return out


def test_oversized_and_malformed_requests_are_refused(daemon):
    d, web, token = daemon
    auth = f"Authorization: Bearer {token}\r\n".encode()
    ten_mb = 10 * 1024 * 1024
    # declared 10 MB: refused from the headers, before the body is read
    reply = _raw_http(web.port, b"POST /api/queue HTTP/1.1\r\nHost: x\r\n" + auth +
                      f"Content-Type: application/json\r\nContent-Length: {ten_mb}\r\n\r\n".encode(),
                      read_first=True)
    assert reply.startswith(b"HTTP/1.1 413"), reply[:200]
    # 10 MB chunked (no length): cut off at the limit
    chunk = b"a" * 65536
    chunks = [f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n"] * (ten_mb // len(chunk)) + [b"0\r\n\r\n"]
    reply = _raw_http(web.port, b"POST /api/queue HTTP/1.1\r\nHost: x\r\n" + auth +
                      b"Transfer-Encoding: chunked\r\n\r\n", chunks)
    assert reply.startswith(b"HTTP/1.1 413"), reply[:200]
    api = Client(web.url, token)
    st, r = api("POST", "/api/queue", {"procedure": "24pos.yaml", "params": {"x": "a" * (MAX_BODY + 1)}})
    assert st == 413
    conn = http.client.HTTPConnection("127.0.0.1", web.port, timeout=10)
    for body in (b"not json", b"[1, 2]", b'{"procedure": 5}', b'{"procedure": "24pos.yaml", "position": -1}'):
        conn.request("POST", "/api/queue", body, {"Authorization": f"Bearer {token}"})
        resp = conn.getresponse()
        assert resp.status == 400, (body, resp.status, resp.read())
        resp.read()
    conn.request("POST", "/api/queue/1/move", b'{"position": "x"}', {"Authorization": f"Bearer {token}"})
    resp = conn.getresponse()
    assert resp.status == 400 and b"position" in resp.read()
    conn.close()
    assert api("GET", "/api/queue")[1]["jobs"] == []  # nothing was queued by any of it
    assert api("GET", "/api/status")[1]["state"] == "idle"
    # the page and its assets are served from the package without the token; no outside URL
    st, page = api("GET", "/", token=None)
    assert st == 200 and "/static/app.js" in page and "http" not in page.replace("http-token", "")
    st, js = api("GET", "/static/app.js", token=None)
    assert st == 200 and "Authorization" in js and "https://" not in js and "http://" not in js
    assert api("GET", "/static/../web.py", token=None)[0] == 404
    assert api("GET", "/static/web.py", token=None)[0] == 404


def test_open_read_lets_views_through_but_never_control(daemon):
    d, _web, token = daemon
    web = WebServer(WebApi(d, token, open_read=True, procedures_dir=ROOT / "procedures"))
    web.start()
    try:
        api = Client(web.url)
        assert api("GET", "/api/status", token=None)[0] == 200
        assert api("GET", "/api/runs", token=None)[0] == 200
        assert api("GET", "/api/live?since=0", token=None)[0] == 200
        for method, path in (("POST", "/api/queue"), ("POST", "/api/pause"), ("POST", "/api/abort"),
                             ("POST", "/api/queue/clear"), ("DELETE", "/api/queue/1"), ("POST", "/api/resume")):
            assert api(method, path, {"procedure": "24pos.yaml"}, token=None)[0] == 401, path
        assert api("GET", "/api/queue")[1]["jobs"] == []
    finally:
        web.close()


def test_token_file_readable_by_others_is_refused(tmp_path):
    from rigctl.service.web import load_or_create_token
    p = tmp_path / "tok"
    t = load_or_create_token(p)
    assert stat.S_IMODE(p.stat().st_mode) == 0o600 and load_or_create_token(p) == t
    os.chmod(p, 0o644)
    with pytest.raises(PermissionError, match="chmod 600"):
        load_or_create_token(p)


def test_live_feed_bin_means_match_numpy():
    rng = np.random.default_rng(7)
    rate, n = 400.0, 4000
    t = 3.0 + np.arange(n) / rate
    f = rng.normal(0, 1, (n, 3)) + [0, 0, 9.8]
    w = rng.normal(0, 0.01, (n, 3))
    feed = LiveFeed(bin_s=0.1, history_s=300)
    cuts = np.sort(rng.choice(np.arange(1, n), 60, replace=False))
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, n]):  # blocks of random sizes, as a link delivers
        feed.add_imu(_Block(t[a:b], f[a:b], w[a:b]))
    got = feed.since(0)
    # independent: bin index floor(t / 0.1), mean per bin; the last (open) bin is not emitted yet
    keys = np.floor(t / 0.1)
    uniq = np.unique(keys)[:-1]
    want_f = np.array([f[keys == k].mean(axis=0) for k in uniq])
    want_w = np.array([w[keys == k].mean(axis=0) for k in uniq])
    assert got["samples"] == n and len(got["imu"]) == len(uniq)
    np.testing.assert_allclose([p["t"] for p in got["imu"]], (uniq + 0.5) * 0.1, rtol=0, atol=1e-9)
    np.testing.assert_allclose([p["f"] for p in got["imu"]], want_f, rtol=0, atol=1e-12)
    np.testing.assert_allclose([p["w"] for p in got["imu"]], want_w, rtol=0, atol=1e-12)
    assert len(feed.since(got["seq"] - 3)["imu"]) == 3


class _Block:
    def __init__(self, t, f, w):
        self.time, self.specific_force, self.angular_rate = t, f, w
        self.temperature = np.full(len(t), 25.0)
        self.counter = np.arange(len(t), dtype=np.uint64)

    def __len__(self):
        return len(self.time)


def test_queue_operations_from_the_cli(daemon, capsys):
    from rigctl.cli import main

    d, _web, _token = daemon
    sock = ["--socket", str(d.socket_path)]
    warm = str(ROOT / "procedures" / "warmup.yaml")

    def cli(*argv):
        code = main([*argv, *sock])
        out, err = capsys.readouterr()
        return code, out, err

    assert cli("queue", "stop")[0] == 0
    assert cli("submit", warm, "-p", "warmup=5 s")[0] == 0
    code, out, _ = cli("submit", warm, "-p", "warmup=6 s", "--position", "1")
    assert code == 0 and out == "job 2 queued at place 1\n"
    code, _, err = cli("submit", warm, "-p", "warmup=6 s")
    assert code == 2 and "already runs" in err  # a duplicate
    assert control.request(d.socket_path, "queue")["queued"] == [2, 1]
    assert cli("queue", "move", "2", "2")[0] == 0
    assert control.request(d.socket_path, "queue")["queued"] == [1, 2]
    assert cli("queue", "remove", "1")[0] == 0
    assert control.request(d.socket_path, "queue")["queued"] == [2]
    for bad in (["queue", "move", "2", "0"], ["queue", "remove"], ["queue", "remove", "7"],
                ["queue", "history", "1", "2"], ["submit", warm, "--position", "0"]):
        code, _, err = cli(*bad)
        assert code == 2 and err.count("\n") == 1, (bad, err)
    code, out, _ = cli("queue", "history", "1", "--json")
    assert code == 0 and json.loads(out)["jobs"][0]["state"] == "removed"

    # readable text: aligned columns, one fact per line; --json: the daemon's whole reply
    code, out, _ = cli("queue")
    lines = out.splitlines()
    assert code == 0 and lines[0].split() == ["PLACE", "JOB", "STATE", "WHAT", "PARAMETERS", "SUBMITTED", "(UTC)",
                                              "ENDED", "(UTC)", "MESSAGE"]
    col = lines[0].index("STATE")
    assert [ln[col:].split()[0] for ln in lines[1:3]] == ["queued", "removed"] and lines[1].split()[:2] == ["1", "2"]
    assert lines[-1] == "queue stopped, 1 queued"
    code, out, _ = cli("status")
    assert code == 0 and re.fullmatch(r"state: +idle since \d\d:\d\d:\d\dZ\njob: +none\nqueue: +1 queued, queue stopped\n", out), out
    code, out, _ = cli("status", "--json")
    assert code == 0 and json.loads(out) == {**control.request(d.socket_path, "status"), "since_utc": json.loads(out)["since_utc"]}
    code, out, err = cli("pause", "--json")
    assert code == 1 and json.loads(out)["ok"] is False and err.count("\n") == 1
    # logs -n N prints N lines, a message of several lines on one
    assert cli("queue", "start")[0] == 0
    wait_job(Client(_web.url, _token), 2)
    run_dir = Path(next(j for j in control.request(d.socket_path, "queue")["jobs"] if j["id"] == 2)["run_dir"])
    with open(run_dir / "run.log.jsonl", "a") as fh:
        fh.write(json.dumps({"utc": "2026-01-01T00:00:00Z", "kind": "error", "message": "a\nb\nc"}) + "\n")
    total = len((run_dir / "run.log.jsonl").read_text().splitlines())
    for n in (1, 3, total + 5):
        code, out, _ = cli("logs", "-n", str(n))
        assert code == 0 and len(out.splitlines()) == min(n, total), out
    assert out.splitlines()[-1].endswith("error    a / b / c")
