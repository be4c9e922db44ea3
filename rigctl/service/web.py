"""The daemon's HTTP API and web page (``rigctl serve --http HOST:PORT``), see docs/daemon.md.

Starlette application served by uvicorn in a thread of the daemon. Every API request goes
through the same handlers as the Unix socket (:meth:`rigctl.service.daemon.Daemon.handle`), so the
two interfaces cannot disagree. Rules:

* Bound to 127.0.0.1 unless the operator names another address.
* Control (submit, queue operations, pause, resume, abort) needs ``Authorization: Bearer
  TOKEN``; the token is created by ``rigctl serve`` in a file of mode 0600. Read-only views
  need it too unless the daemon was started with ``--http-open-read``. A header, not a cookie:
  another site open in the same browser cannot send it.
* Request bodies are at most :data:`MAX_BODY` bytes (a larger Content-Length is refused with
  413 before the body is read; a chunked body is cut off at the limit).
* Procedures are submitted by name from the daemon's procedures directory, never by path.
* Every asset of the page is served from the package (labs are often offline: no CDN).
"""
from __future__ import annotations

import asyncio
import hmac
import json
import math
import os
import secrets
import socket
import threading
import time
import traceback
from pathlib import Path
from typing import Any

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import FileResponse, Response, StreamingResponse
from starlette.routing import Route

from ..errors import EXIT_INVALID, RigctlError

MAX_BODY = 64 * 1024
MAX_STREAMS = 32           # live-event streams open at once
EVENT_PERIOD_S = 0.5       # one status + live batch per stream this often
TICKET_S = 120.0           # a report ticket opens that report without the token this long
STATIC = Path(__file__).resolve().parent / "web_static"
ASSETS = {"app.js": "text/javascript; charset=utf-8", "app.css": "text/css; charset=utf-8"}


# -- token -------------------------------------------------------------------------------------
def load_or_create_token(path: Path) -> str:
    """The token in ``path``; a new random one (256 bits) written with mode 0600 if absent.
    An existing file readable by others is refused (the token would not be secret)."""
    path = Path(path)
    if path.exists():
        mode = path.stat().st_mode & 0o777
        if mode & 0o077:
            raise PermissionError(f"{path} is readable by others (mode {mode:o}): chmod 600 it")
        token = path.read_text(encoding="ascii").strip()
        if len(token) < 16:
            raise PermissionError(f"{path}: token shorter than 16 characters")
        return token
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    token = secrets.token_urlsafe(32)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w", encoding="ascii") as fh:
        fh.write(token + "\n")
    return token


def parse_hostport(text: str) -> tuple[str, int]:
    """``HOST:PORT`` or ``PORT`` (host 127.0.0.1); ValueError when malformed."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]") if sep else "127.0.0.1"
    if not port.isdigit() or not 0 <= int(port) <= 65535 or not host:
        raise ValueError(f"--http {text!r}: expected HOST:PORT, e.g. 127.0.0.1:8470")
    return host, int(port)


# -- JSON --------------------------------------------------------------------------------------
def _clean(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    return obj


def _json(obj: Any, status: int = 200, headers: dict[str, str] | None = None) -> Response:
    return Response(json.dumps(_clean(obj), default=str), status_code=status,
                    media_type="application/json", headers=headers)


def _error(status: int, text: str) -> Response:
    hdr = {"WWW-Authenticate": 'Bearer realm="rigctl"'} if status == 401 else None
    return _json({"ok": False, "error": text}, status, hdr)


def _reply(reply: dict[str, Any]) -> Response:
    """A daemon reply as HTTP: ok -> 200; refused as invalid -> 400; else refused -> 409."""
    if reply.get("ok"):
        return _json(reply)
    return _json(reply, 400 if reply.get("exit_code") == EXIT_INVALID else 409)


# -- body limit --------------------------------------------------------------------------------
class BodyLimit:
    """ASGI middleware: refuse request bodies over ``limit`` bytes with 413."""

    def __init__(self, app: Any, limit: int = MAX_BODY) -> None:
        self.app, self.limit = app, limit

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        length = dict(scope["headers"]).get(b"content-length")
        if length is not None and (not length.isdigit() or int(length) > self.limit):
            await _error(413, f"request body larger than {self.limit} bytes")(scope, receive, send)
            return
        seen, started, refused = 0, False, False
        too_large = _error(413, f"request body larger than {self.limit} bytes")

        async def limited_receive() -> dict:
            nonlocal seen, refused
            msg = await receive()
            if msg["type"] == "http.request" and not refused:
                seen += len(msg.get("body", b""))
                if seen > self.limit:  # answer 413 now; the application sees a disconnect
                    refused = True
                    if not started:
                        await too_large(scope, receive, send)
                    return {"type": "http.disconnect"}
            return msg

        async def tracking_send(msg: dict) -> None:
            nonlocal started
            if refused:
                return  # the 413 is the answer
            started = started or msg["type"] == "http.response.start"
            await send(msg)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except Exception:
            if not refused:
                raise


# -- the application -----------------------------------------------------------------------------
class WebApi:
    """Routes of the HTTP API on a :class:`rigctl.service.daemon.Daemon`."""

    def __init__(self, daemon: Any, token: str, open_read: bool = False,
                 procedures_dir: Path | None = None) -> None:
        self.d, self.token, self.open_read = daemon, token, open_read
        self.procedures_dir = Path(procedures_dir).resolve() if procedures_dir else None
        self.streams = 0
        self.tickets: dict[str, tuple[str, float]] = {}  # ticket -> (run, expiry on time.monotonic)
        self._report_lock = threading.Lock()
        routes = [
            Route("/", self.page), Route("/static/{name}", self.asset),
            Route("/api/status", self.status), Route("/api/queue", self.queue, methods=["GET", "POST"]),
            Route("/api/queue/clear", self.control("queue_clear"), methods=["POST"]),
            Route("/api/queue/start", self.control("queue_start"), methods=["POST"]),
            Route("/api/queue/stop", self.control("queue_stop"), methods=["POST"]),
            Route("/api/queue/{job:int}", self.queue_remove, methods=["DELETE"]),
            Route("/api/queue/{job:int}/move", self.queue_move, methods=["POST"]),
            Route("/api/history", self.history), Route("/api/logs", self.logs),
            Route("/api/procedures", self.procedures),
            Route("/api/pause", self.control("pause"), methods=["POST"]),
            Route("/api/resume", self.control("resume"), methods=["POST"]),
            Route("/api/abort", self.control("abort"), methods=["POST"]),
            Route("/api/runs", self.runs), Route("/api/runs/{run}/report", self.report),
            Route("/api/runs/{run}/ticket", self.ticket, methods=["POST"]),
            Route("/api/live", self.live), Route("/api/events", self.events),
        ]
        self.app = BodyLimit(Starlette(routes=routes))

    # -- helpers -------------------------------------------------------------------------------
    def _denied(self, request: Request, control: bool) -> Response | None:
        """None when the request may proceed; else the 401 response."""
        if not control and self.open_read:
            return None
        auth = request.headers.get("authorization", "")
        scheme, _, given = auth.partition(" ")
        if scheme.lower() != "bearer" or not hmac.compare_digest(given.strip().encode(), self.token.encode()):
            return _error(401, "a valid token is required (Authorization: Bearer TOKEN; "
                               "the token is in the file 'rigctl serve' printed)")
        return None

    async def _call(self, cmd: str, args: dict[str, Any] | None = None) -> dict[str, Any]:
        from .control import ProtocolError, validate_request
        try:
            cmd, args = validate_request({"v": 1, "cmd": cmd, "args": args or {}})
        except ProtocolError as exc:
            return {"ok": False, "error": str(exc), "exit_code": EXIT_INVALID}
        return await run_in_threadpool(self.d.handle, cmd, args)

    @staticmethod
    async def _body(request: Request) -> dict[str, Any] | Response:
        raw = await request.body()
        if not raw.strip():
            return {}
        try:
            obj = json.loads(raw)
        except (ValueError, UnicodeDecodeError) as exc:
            return _error(400, f"body is not JSON: {exc}")
        return obj if isinstance(obj, dict) else _error(400, "body must be a JSON object")

    def control(self, cmd: str):
        async def endpoint(request: Request) -> Response:
            if (denied := self._denied(request, True)) is not None:
                return denied
            body = await self._body(request)
            if isinstance(body, Response):
                return body
            args: dict[str, Any] = {}
            if cmd == "pause" and body.get("deferred") is True:
                args["deferred"] = True
            if cmd == "resume" and "run" in body:
                run = self._run_dir(str(body["run"]))
                if run is None:
                    return _error(404, f"no run {body['run']!r}")
                args["run"] = str(run)
            return _reply(await self._call(cmd, args))
        return endpoint

    def _run_dir(self, name: str) -> Path | None:
        """The run directory called ``name`` directly inside the daemon's runs directory."""
        if not name or name.startswith(".") or "/" in name or "\\" in name or name in ("..",):
            return None
        d = self.d.runs_dir / name
        return d if d.is_dir() and d.resolve().parent == self.d.runs_dir else None

    # -- page ----------------------------------------------------------------------------------
    async def page(self, request: Request) -> Response:
        return FileResponse(STATIC / "index.html", media_type="text/html; charset=utf-8",
                            headers=_page_headers())

    async def asset(self, request: Request) -> Response:
        name = request.path_params["name"]
        if name not in ASSETS:
            return _error(404, "no such asset")
        return FileResponse(STATIC / name, media_type=ASSETS[name], headers=_page_headers())

    # -- read-only views -------------------------------------------------------------------------
    async def status(self, request: Request) -> Response:
        if (denied := self._denied(request, False)) is not None:
            return denied
        return _reply(await self._call("status"))

    async def history(self, request: Request) -> Response:
        if (denied := self._denied(request, False)) is not None:
            return denied
        try:
            limit = int(request.query_params.get("limit", "50"))
        except ValueError:
            return _error(400, "limit must be an integer")
        return _reply(await self._call("history", {"limit": limit}))

    async def logs(self, request: Request) -> Response:
        if (denied := self._denied(request, False)) is not None:
            return denied
        try:
            n = int(request.query_params.get("lines", "50"))
        except ValueError:
            return _error(400, "lines must be an integer")
        return _reply(await self._call("logs", {"lines": n}))

    def _procedure_names(self) -> list[str]:
        if self.procedures_dir is None or not self.procedures_dir.is_dir():
            return []
        return sorted(p.name for p in self.procedures_dir.glob("*.yaml") if p.is_file())

    async def procedures(self, request: Request) -> Response:
        if (denied := self._denied(request, False)) is not None:
            return denied
        return _json({"ok": True, "directory": str(self.procedures_dir or ""),
                      "procedures": self._procedure_names()})

    async def queue(self, request: Request) -> Response:
        if request.method == "GET":
            if (denied := self._denied(request, False)) is not None:
                return denied
            return _reply(await self._call("queue"))
        if (denied := self._denied(request, True)) is not None:
            return denied
        body = await self._body(request)
        if isinstance(body, Response):
            return body
        name = body.get("procedure")
        if not isinstance(name, str) or name not in self._procedure_names():
            return _error(400, f"procedure must be one of {self._procedure_names()} "
                               f"(the daemon's procedures directory {self.procedures_dir})")
        args: dict[str, Any] = {"procedure": str(self.procedures_dir / name),
                                "params": body.get("params") or {}}
        if "position" in body:
            args["position"] = body["position"]
        return _reply(await self._call("submit", args))

    async def queue_remove(self, request: Request) -> Response:
        if (denied := self._denied(request, True)) is not None:
            return denied
        return _reply(await self._call("queue_remove", {"job": request.path_params["job"]}))

    async def queue_move(self, request: Request) -> Response:
        if (denied := self._denied(request, True)) is not None:
            return denied
        body = await self._body(request)
        if isinstance(body, Response):
            return body
        return _reply(await self._call("queue_move", {"job": request.path_params["job"],
                                                      "position": body.get("position")}))

    # -- runs and reports ------------------------------------------------------------------------
    def _list_runs(self) -> list[dict[str, Any]]:
        with self.d.cv:
            jobs = {Path(j.run_dir).name: j for j in self.d.jobs if j.run_dir}
        out = []
        dirs = [p for p in self.d.runs_dir.iterdir() if p.is_dir() and not p.name.startswith(".")]
        for d in sorted(dirs, key=lambda p: p.stat().st_mtime, reverse=True)[:200]:
            ck = d / "checkpoint.json"
            if not ck.exists() and not (d / "recording.h5").exists():
                continue
            info: dict[str, Any] = {"id": d.name, "status": None, "procedure": None, "updated_utc": None,
                                    "analysis": None}
            try:
                c = json.loads(ck.read_text())
                info.update(status=c.get("status"), procedure=Path(str(c.get("procedure_path", ""))).name,
                            updated_utc=c.get("updated_utc"), analysis=c.get("analysis") or None)
            except (OSError, ValueError):
                pass
            j = jobs.get(d.name)
            if j is not None:
                info.update(job=j.id, job_state=j.state, message=j.message)
            info["report"] = f"/api/runs/{d.name}/report"
            info["report_ready"] = (d / "report.html").exists()
            out.append(info)
        return out

    async def runs(self, request: Request) -> Response:
        if (denied := self._denied(request, False)) is not None:
            return denied
        return _json({"ok": True, "runs": await run_in_threadpool(self._list_runs)})

    def _build_report(self, run_dir: Path) -> Path:
        from ..report.report import REPORT_HTML
        from ..report.report_build import build_report
        target = run_dir / REPORT_HTML
        with self._report_lock:  # one report at a time: matplotlib is not thread-safe
            if not target.exists():
                build_report(run_dir)
        return target

    async def ticket(self, request: Request) -> Response:
        """A key that opens this run's report for :data:`TICKET_S` seconds without the token, so
        the page can open the report in a new tab (a link cannot carry the header)."""
        if (denied := self._denied(request, False)) is not None:
            return denied
        d = self._run_dir(request.path_params["run"])
        if d is None:
            return _error(404, f"no run {request.path_params['run']!r}")
        now = time.monotonic()
        self.tickets = {k: v for k, v in self.tickets.items() if v[1] > now}
        key = secrets.token_urlsafe(24)
        self.tickets[key] = (d.name, now + TICKET_S)
        return _json({"ok": True, "url": f"/api/runs/{d.name}/report?ticket={key}", "valid_s": TICKET_S})

    async def report(self, request: Request) -> Response:
        held = self.tickets.get(request.query_params.get("ticket", ""))
        ticket_ok = held is not None and held[0] == request.path_params["run"] and held[1] > time.monotonic()
        if not ticket_ok and (denied := self._denied(request, False)) is not None:
            return denied
        d = self._run_dir(request.path_params["run"])
        if d is None:
            return _error(404, f"no run {request.path_params['run']!r}")
        with self.d.cv:
            busy = self.d.current is not None and Path(self.d.current.run_dir or "/").name == d.name
        if busy and not (d / "report.html").exists():
            return _error(409, "the run is still recording or analysing; its report is made when it ends")
        try:
            path = await run_in_threadpool(self._build_report, d)
        except RigctlError as exc:  # a recording the report cannot read: its one line
            return _error(422 if exc.exit_code == EXIT_INVALID else 500, f"report failed: {exc}")
        except Exception as exc:  # noqa: BLE001 - a bug: one line to the client, traceback in the log
            self.d.log("error", f"report of {d.name} failed: {type(exc).__name__}: {exc}",
                       traceback=traceback.format_exc())
            return _error(500, f"report failed: {type(exc).__name__}: {exc} (traceback in the daemon log)")
        return FileResponse(path, media_type="text/html; charset=utf-8")

    # -- live ------------------------------------------------------------------------------------
    async def live(self, request: Request) -> Response:
        if (denied := self._denied(request, False)) is not None:
            return denied
        try:
            since = int(request.query_params.get("since", "0"))
        except ValueError:
            return _error(400, "since must be an integer")
        return _json({"ok": True, **self.d.live.since(since)})

    async def events(self, request: Request) -> Response:
        """Server-sent events: ``status`` and ``live`` (new decimated points) every 0.5 s."""
        if (denied := self._denied(request, False)) is not None:
            return denied
        if self.streams >= MAX_STREAMS:
            return _error(503, f"at most {MAX_STREAMS} live streams at once")
        self.streams += 1

        async def gen():
            seq = -1
            try:
                while not await request.is_disconnected():
                    st = await self._call("status")
                    batch = self.d.live.since(max(seq, 0), limit=3000 if seq < 0 else 500)
                    seq = batch["seq"]
                    yield f"event: status\ndata: {json.dumps(_clean(st))}\n\n"
                    yield f"event: live\ndata: {json.dumps(_clean(batch))}\n\n"
                    await asyncio.sleep(EVENT_PERIOD_S)
            finally:
                self.streams -= 1

        return StreamingResponse(gen(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})


def _page_headers() -> dict[str, str]:
    return {"Cache-Control": "no-store", "X-Content-Type-Options": "nosniff", "X-Frame-Options": "DENY",
            "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; frame-ancestors 'none'",
            "Referrer-Policy": "no-referrer"}


class WebServer:
    """uvicorn serving a :class:`WebApi` in a background thread of the daemon."""

    def __init__(self, api: WebApi, host: str = "127.0.0.1", port: int = 0, log: Any = None) -> None:
        import uvicorn

        self.api, self.host, self.log = api, host, log or (lambda kind, msg, **kw: None)
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.sock = socket.socket(family, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind((host, port))  # bound here: a busy port fails in 'rigctl serve', not later
        self.sock.listen(1024)
        self.port = self.sock.getsockname()[1]
        config = uvicorn.Config(api.app, log_level="warning", access_log=False, lifespan="off",
                                timeout_keep_alive=5, limit_concurrency=2000, backlog=1024,
                                server_header=False, date_header=False)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self._run, name="rigctl-http", daemon=True)

    def _run(self) -> None:
        asyncio.run(self.server.serve(sockets=[self.sock]))

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def start(self, timeout: float = 10.0) -> None:
        self.thread.start()
        end = time.monotonic() + timeout
        while not self.server.started and self.thread.is_alive() and time.monotonic() < end:
            time.sleep(0.02)
        if not self.server.started:
            raise RuntimeError(f"the HTTP server did not start on {self.url}")

    def close(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=5)
        self.sock.close()
