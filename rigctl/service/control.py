"""The daemon's control API: JSON over a Unix-domain socket, and the client verbs.

Security: the socket lives in a directory of mode 0700 owned by the daemon's user and is itself
mode 0600; on every connection the server reads the peer's credentials (``SO_PEERCRED``) and
refuses any uid other than its own. One request per connection: a single JSON object of at
most :data:`MAX_MESSAGE` bytes ending in a newline, checked against :data:`SCHEMA` (unknown
commands, unknown or mistyped arguments are refused); one JSON reply. Nothing runs a shell.

Request ``{"v": 1, "cmd": "status", "args": {}}``; reply ``{"ok": true, ...}`` or
``{"ok": false, "error": "..."}``.
"""
from __future__ import annotations

import json
import os
import socket
import stat
import struct
import threading
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import EXIT_FAILED, EXIT_INVALID, RigctlError, RunFailure

PROTOCOL_VERSION = 1
MAX_MESSAGE = 64 * 1024
CONN_TIMEOUT_S = 5.0

#: command -> {argument: (allowed types, required)}
SCHEMA: dict[str, dict[str, tuple[tuple[type, ...], bool]]] = {
    "ping": {},
    "status": {},
    "queue": {},
    "submit": {"procedure": ((str,), True), "params": ((dict,), False), "position": ((int,), False)},
    "queue_remove": {"job": ((int,), True)},
    "queue_move": {"job": ((int,), True), "position": ((int,), True)},
    "queue_clear": {},
    "queue_start": {},
    "queue_stop": {},
    "history": {"limit": ((int,), False)},
    "pause": {"deferred": ((bool,), False)},
    "resume": {"run": ((str,), False)},
    "abort": {},
    "logs": {"lines": ((int,), False)},
}


class ProtocolError(ValueError):
    """A malformed, oversized or unauthorised request."""


def default_socket_path() -> Path:
    """``$RIGCTL_SOCKET``, else ``$XDG_RUNTIME_DIR/rigctl/rigctl.sock``, else
    ``/tmp/rigctl-<uid>/rigctl.sock``."""
    if os.environ.get("RIGCTL_SOCKET"):
        return Path(os.environ["RIGCTL_SOCKET"])
    base = os.environ.get("XDG_RUNTIME_DIR")
    if base and Path(base).is_dir():
        return Path(base) / "rigctl" / "rigctl.sock"
    return Path(f"/tmp/rigctl-{os.getuid()}") / "rigctl.sock"


def validate_request(obj: Any) -> tuple[str, dict[str, Any]]:
    """(command, args) of a well-formed request, else ProtocolError saying what is wrong."""
    if not isinstance(obj, dict):
        raise ProtocolError("request must be a JSON object")
    extra = set(obj) - {"v", "cmd", "args"}
    if extra:
        raise ProtocolError(f"unknown request fields {sorted(extra)}")
    if obj.get("v") != PROTOCOL_VERSION:
        raise ProtocolError(f"protocol version must be {PROTOCOL_VERSION}")
    cmd = obj.get("cmd")
    if not isinstance(cmd, str) or cmd not in SCHEMA:
        raise ProtocolError(f"unknown command {cmd!r}; one of {', '.join(SCHEMA)}")
    args = obj.get("args", {})
    if not isinstance(args, dict):
        raise ProtocolError("args must be a JSON object")
    spec = SCHEMA[cmd]
    for key, value in args.items():
        if key not in spec:
            raise ProtocolError(f"{cmd}: unknown argument {key!r}")
        types, _ = spec[key]
        if (isinstance(value, bool) and bool not in types) or not isinstance(value, types):
            raise ProtocolError(f"{cmd}: argument {key!r} must be {'/'.join(t.__name__ for t in types)}")
    for key, (_, required) in spec.items():
        if required and key not in args:
            raise ProtocolError(f"{cmd}: missing argument {key!r}")
    if cmd == "submit":
        params = args.get("params", {})
        if not all(isinstance(k, str) and isinstance(v, (str, int, float, bool)) for k, v in params.items()):
            raise ProtocolError("submit: params must map names to scalars")
    if cmd == "logs" and not 0 < args.get("lines", 50) <= 10000:
        raise ProtocolError("logs: lines must be in 1..10000")
    if cmd == "history" and not 0 < args.get("limit", 50) <= 10000:
        raise ProtocolError("history: limit must be in 1..10000")
    if not 0 <= args.get("position", 0) <= 100000:
        raise ProtocolError(f"{cmd}: position must be in 0..100000")
    return cmd, args


def peer_uid(conn: socket.socket) -> int:
    """The uid of the process at the other end of a Unix socket (SO_PEERCRED)."""
    creds = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    _pid, uid, _gid = struct.unpack("3i", creds)
    return uid


def _read_message(conn: socket.socket) -> bytes:
    buf = bytearray()
    while b"\n" not in buf:
        chunk = conn.recv(4096)
        if not chunk:
            break
        buf += chunk
        if len(buf) > MAX_MESSAGE:
            raise ProtocolError(f"message larger than {MAX_MESSAGE} bytes")
    line = bytes(buf).split(b"\n", 1)[0]
    if len(line) > MAX_MESSAGE:
        raise ProtocolError(f"message larger than {MAX_MESSAGE} bytes")
    return line


def _send(conn: socket.socket, obj: dict[str, Any]) -> None:
    """Send the reply, then drain (a bounded amount of) unread input before the close, so the
    client reads the reply instead of a connection reset."""
    try:
        conn.sendall(json.dumps(obj).encode() + b"\n")
        conn.shutdown(socket.SHUT_WR)
        conn.settimeout(0.5)
        left = 4 * MAX_MESSAGE
        while left > 0 and (chunk := conn.recv(65536)):
            left -= len(chunk)
    except OSError:
        pass


def prepare_socket_dir(path: Path) -> None:
    """Create the socket's directory 0700, or check an existing one is ours and private."""
    d = path.parent
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    st = d.stat()
    if st.st_uid != os.getuid():
        raise PermissionError(f"{d} belongs to uid {st.st_uid}, not to us ({os.getuid()})")
    if stat.S_IMODE(st.st_mode) & 0o077:
        os.chmod(d, 0o700)


class ControlServer:
    """Accepts connections on a Unix socket and answers each request with ``handler``."""

    def __init__(self, path: Path, handler: Callable[[str, dict[str, Any]], dict[str, Any]],
                 log: Callable[..., None] | None = None) -> None:
        self.path, self.handler = Path(path), handler
        self.log = log or (lambda kind, msg, **kw: None)
        prepare_socket_dir(self.path)
        if self.path.exists() or self.path.is_symlink():
            if not stat.S_ISSOCK(self.path.lstat().st_mode):
                raise FileExistsError(f"{self.path} exists and is not a socket")
            if ping(self.path):
                raise RunFailure(f"{self.path}: a rigctl daemon already listens on this socket (rigctl status "
                                 "shows it; stop it first, or give this one another --socket)")
            self.path.unlink()
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o177)
        try:
            self.sock.bind(str(self.path))
        finally:
            os.umask(old)
        os.chmod(self.path, 0o600)
        self.sock.listen(128)
        self.sock.settimeout(0.5)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, name="rigctl-control", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def close(self) -> None:
        self._stop.set()
        if self.thread.ident is not None:  # closed before start() too (rigctl serve stopped early)
            self.thread.join(timeout=2)
        self.sock.close()
        try:
            self.path.unlink()
        except FileNotFoundError:
            pass

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except socket.timeout:
                continue
            except OSError:
                break
            threading.Thread(target=self._handle, args=(conn,), daemon=True).start()

    def _handle(self, conn: socket.socket) -> None:
        with conn:
            conn.settimeout(CONN_TIMEOUT_S)
            try:
                uid = peer_uid(conn)
                if uid != os.getuid():
                    self.log("warning", f"control: refused a client of uid {uid}")
                    _send(conn, {"ok": False, "error": "permission denied: not the daemon's owner"})
                    return
                raw = _read_message(conn)
                try:
                    obj = json.loads(raw)
                except (ValueError, UnicodeDecodeError) as exc:
                    raise ProtocolError(f"not JSON: {exc}") from None
                cmd, args = validate_request(obj)
            except ProtocolError as exc:
                self.log("warning", f"control: rejected a request: {exc}")
                _send(conn, {"ok": False, "error": str(exc), "exit_code": EXIT_INVALID})
                return
            except OSError:
                return
            try:
                reply = self.handler(cmd, args)
            except RigctlError as exc:  # the handler's refusal: its one line and exit code
                self.log("warning", f"control: {cmd} refused: {exc}")
                reply = {"ok": False, "error": str(exc), "exit_code": exc.exit_code}
            except Exception as exc:  # noqa: BLE001 - a bug; the daemon keeps serving
                self.log("error", f"control: {cmd} failed: {type(exc).__name__}: {exc}",
                         traceback=traceback.format_exc())
                reply = {"ok": False, "error": f"{type(exc).__name__}: {exc} (a bug: traceback in the "
                         "daemon log)", "exit_code": EXIT_FAILED}
            _send(conn, reply)


def request(path: Path, cmd: str, args: dict[str, Any] | None = None,
            timeout: float = 10.0) -> dict[str, Any]:
    """Send one request to the daemon; its reply. ConnectionError when nobody listens."""
    msg = json.dumps({"v": PROTOCOL_VERSION, "cmd": cmd, "args": args or {}}).encode() + b"\n"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout)
        try:
            s.connect(str(path))
        except (FileNotFoundError, ConnectionRefusedError) as exc:
            raise ConnectionError(f"no rigctl daemon at {path} ({exc.strerror}); "
                                  "start one with 'rigctl serve'") from None
        s.sendall(msg)
        s.shutdown(socket.SHUT_WR)
        data = bytearray()
        while chunk := s.recv(65536):
            data += chunk
    try:
        return json.loads(bytes(data) or b"{}")
    except ValueError:
        return {"ok": False, "error": "unreadable reply from the daemon"}


def ping(path: Path) -> bool:
    try:
        return bool(request(path, "ping", timeout=2.0).get("ok"))
    except (ConnectionError, OSError):
        return False


def wait_for_socket(path: Path, timeout: float = 20.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if ping(path):
            return True
        time.sleep(0.05)
    return False
