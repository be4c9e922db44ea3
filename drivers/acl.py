"""ACL-flavoured ASCII turntable command set (docs/protocols.md section 2): parser and formatter.

Used by the emulated server (``parse_message`` -> :class:`AclRequest`; ``format_*`` replies) and
by the driver (``command`` / ``query`` builders; ``parse_reply`` and friends). Pure functions, no I/O.

Syntax: colon-separated, case-insensitive mnemonics that may be abbreviated to any unique prefix
(``:M:P 1`` = ``:MODE:POSITION 1``); arguments after a space, comma-separated; a trailing ``?``
makes a query; ``;`` chains commands, a chained command without a leading colon stays in the
previous command's subsystem (``:MODE:POSITION 1;RATE 2``). Lines end in LF (CR LF accepted).
One request line, one reply line: ``OK``, a value, or ``ERR <code>,<text>``; chained replies are
joined with ``;``. Angles on the wire are degrees, rates deg/s, accelerations deg/s^2.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

from rigctl.errors import DeviceError

TERMINATOR = b"\n"
DEFAULT_TCP_PORT = 9878


class AclCode(IntEnum):
    """SCPI-like error codes."""

    NO_ERROR = 0
    COMMAND_ERROR = -100
    EXECUTION_ERROR = -200
    SETTINGS_CONFLICT = -221
    OUT_OF_RANGE = -222


class AclError(DeviceError):
    """A request was refused (server side) or the reply was an error (driver side): the
    controller answered wrongly (:class:`rigctl.errors.DeviceError`, exit code 1)."""

    def __init__(self, code: int, text: str) -> None:
        super().__init__(f"{code},{text}")
        self.code = int(code)
        self.text = text


#: Command tree: node -> children. The keys are the canonical long names.
TREE: dict[str, dict] = {
    "INTERLOCK": {"CLOSE": {}, "OPEN": {}, "RESET": {}},
    "MODE": {"POSITION": {}, "RATE": {}, "OFF": {}},
    "DEMAND": {"POSITION": {}, "RATE": {}},
    "LIMIT": {"RATE": {}, "ACCELERATION": {}},
    "READ": {"POSITION": {}, "RATE": {}, "ACCELERATION": {}, "ALL": {}},
    "STATUS": {"AXIS": {}},
    "ABORT": {},
    "SYSTEM": {"ERROR": {}},
}
COMMON = ("*IDN", "*RST", "*CLS")

#: (path, query) pairs that exist. READ:* are queries with or without the '?' (ACT2000 style).
VALID_FORMS: set[tuple[tuple[str, ...], bool]] = {
    (("*IDN",), True), (("*RST",), False), (("*CLS",), False),
    (("INTERLOCK", "CLOSE"), False), (("INTERLOCK", "OPEN"), False), (("INTERLOCK", "RESET"), False),
    (("INTERLOCK",), True),
    (("MODE", "POSITION"), False), (("MODE", "RATE"), False), (("MODE", "OFF"), False),
    (("MODE",), False), (("MODE",), True),
    (("DEMAND", "POSITION"), False), (("DEMAND", "POSITION"), True),
    (("DEMAND", "RATE"), False), (("DEMAND", "RATE"), True),
    (("LIMIT", "RATE"), False), (("LIMIT", "RATE"), True),
    (("LIMIT", "ACCELERATION"), False), (("LIMIT", "ACCELERATION"), True),
    (("READ", "POSITION"), True), (("READ", "RATE"), True), (("READ", "ACCELERATION"), True),
    (("READ", "ALL"), True), (("STATUS", "AXIS"), True), (("ABORT",), False), (("SYSTEM", "ERROR"), True),
}


@dataclass(frozen=True)
class AclRequest:
    """One parsed command: canonical path, query flag and raw argument strings."""

    path: tuple[str, ...]
    query: bool
    args: tuple[str, ...] = ()

    @property
    def name(self) -> str:
        return ":".join(self.path) + ("?" if self.query else "")


def _resolve(token: str, children: dict) -> str:
    t = token.upper()
    if not t:
        raise AclError(AclCode.COMMAND_ERROR, "Empty mnemonic")
    if t in children:
        return t
    cands = [k for k in children if k.startswith(t)]
    if len(cands) == 1:
        return cands[0]
    if not cands:
        raise AclError(AclCode.COMMAND_ERROR, f"Undefined header {token}")
    raise AclError(AclCode.COMMAND_ERROR, f"Ambiguous header {token}")


def _parse_one(text: str, base: tuple[str, ...]) -> AclRequest:
    text = text.strip()
    head, _, argtext = text.partition(" ")
    query = head.endswith("?")
    head = head.rstrip("?")
    args = tuple(a.strip() for a in argtext.split(",")) if argtext.strip() else ()
    if head.startswith("*"):
        name = head.upper()
        if name not in COMMON:
            raise AclError(AclCode.COMMAND_ERROR, f"Undefined header {head}")
        path: tuple[str, ...] = (name,)
    else:
        if head.startswith(":"):
            node, path, tokens = TREE, (), head[1:].split(":")
        else:
            node, path, tokens = TREE, (), head.split(":")
            for p in base:
                node = node[p]
            path = base
        for tok in tokens:
            name = _resolve(tok, node)
            node = node[name]
            path = path + (name,)
    if path and path[0] == "READ" and len(path) == 2:
        query = True            # '?' is optional for READ (ACT2000 compatibility)
    if (path, query) not in VALID_FORMS:
        raise AclError(AclCode.COMMAND_ERROR, f"Command not recognized: {text}")
    return AclRequest(path=path, query=query, args=args)


def parse_message(line: str | bytes) -> list[AclRequest]:
    """Parse one request line (possibly ``;``-chained) into requests; raises AclError(-100)."""
    if isinstance(line, bytes):
        try:
            line = line.decode("ascii")
        except UnicodeDecodeError as exc:
            raise AclError(AclCode.COMMAND_ERROR, "Non-ASCII input") from exc
    line = line.strip()
    if not line:
        raise AclError(AclCode.COMMAND_ERROR, "Empty command")
    out: list[AclRequest] = []
    base: tuple[str, ...] = ()
    for part in line.split(";"):
        req = _parse_one(part, base)
        out.append(req)
        base = req.path[:-1] if len(req.path) > 1 and not req.path[0].startswith("*") else ()
    return out


# --------------------------------------------------------------- argument helpers (server)

def parse_axis(arg: str, n_axes: int, allow_all: bool = False) -> list[int]:
    """Axis argument -> list of 1-based axes (``ALL`` -> every axis when allowed)."""
    a = arg.strip().upper()
    if allow_all and a == "ALL":
        return list(range(1, n_axes + 1))
    try:
        ax = int(a)
    except ValueError:
        raise AclError(AclCode.COMMAND_ERROR, f"Invalid axis {arg!r}") from None
    if not 1 <= ax <= n_axes:
        raise AclError(AclCode.OUT_OF_RANGE, f"Axis {ax} out of range 1..{n_axes}")
    return [ax]


def parse_number(arg: str) -> float:
    """Decimal argument -> float; raises AclError(-100) when not a finite number."""
    try:
        v = float(arg)
    except ValueError:
        raise AclError(AclCode.COMMAND_ERROR, f"Invalid number {arg!r}") from None
    if v != v or v in (float("inf"), float("-inf")):
        raise AclError(AclCode.COMMAND_ERROR, f"Invalid number {arg!r}")
    return v


def expect_args(req: AclRequest, n: int) -> tuple[str, ...]:
    """Check the argument count of a request."""
    if len(req.args) != n:
        raise AclError(AclCode.COMMAND_ERROR, f"{req.name} expects {n} argument(s), got {len(req.args)}")
    return req.args


# ------------------------------------------------------------------------ reply formats

def format_ok() -> str:
    return "OK"


def format_error(code: int, text: str) -> str:
    """Immediate error reply ``ERR <code>,<text>`` (text without ';' or newlines)."""
    return f"ERR {int(code)},{text.replace(';', ',').replace(chr(10), ' ')}"


def format_error_queue_entry(code: int, text: str) -> str:
    """``:SYSTem:ERRor?`` reply, e.g. ``0,"No error"``."""
    return f'{int(code)},"{text}"'


def format_value(v: float) -> str:
    return f"{v:.6f}"


def format_status(word: int) -> str:
    return f"0x{word & 0xFFFF:04X}"


def format_read_all(pos_deg: float, rate_deg_s: float, acc_deg_s2: float, status: int, t_ms: int) -> str:
    return f"{pos_deg:.6f},{rate_deg_s:.6f},{acc_deg_s2:.6f},{format_status(status)},{int(t_ms)}"


def format_replies(replies: list[str]) -> bytes:
    return (";".join(replies)).encode("ascii") + TERMINATOR


# ------------------------------------------------------------------- driver-side helpers

def command(path: str, *args: object) -> bytes:
    """Format a command, e.g. ``command(":DEMAND:POSITION", 1, 90.0)`` -> ``b":DEMAND:POSITION 1,90.000000\\n"``."""
    return _fmt(path, args, False)


def query(path: str, *args: object) -> bytes:
    """Format a query, e.g. ``query(":READ:POSITION", 1)`` -> ``b":READ:POSITION? 1\\n"``."""
    return _fmt(path, args, True)


def _fmt(path: str, args: tuple, q: bool) -> bytes:
    a = ",".join(format_value(x) if isinstance(x, float) else str(x) for x in args)
    return f"{path}{'?' if q else ''}{' ' + a if a else ''}".encode("ascii") + TERMINATOR


def parse_reply(line: str | bytes) -> str:
    """Strip a reply line; raise :class:`AclError` if it is ``ERR code,text``."""
    if isinstance(line, bytes):
        line = line.decode("ascii", "replace")
    line = line.strip()
    if line.startswith("ERR"):
        body = line[3:].strip()
        code, _, text = body.partition(",")
        try:
            raise AclError(int(code), text)
        except ValueError:
            raise AclError(AclCode.COMMAND_ERROR, f"unparseable error reply {line!r}") from None
    return line


def parse_ok(line: str | bytes) -> None:
    """Expect ``OK``."""
    r = parse_reply(line)
    if r != "OK":
        raise AclError(AclCode.COMMAND_ERROR, f"expected OK, got {r!r}")


def parse_float(line: str | bytes) -> float:
    r = parse_reply(line)
    try:
        return float(r)
    except ValueError:
        raise AclError(AclCode.COMMAND_ERROR, f"expected a number, got {r!r}") from None


def parse_status(line: str | bytes) -> int:
    r = parse_reply(line)
    try:
        return int(r, 16)
    except ValueError:
        raise AclError(AclCode.COMMAND_ERROR, f"expected a status word, got {r!r}") from None


@dataclass(frozen=True)
class ReadAll:
    """``:READ:ALL?`` snapshot: position deg, rate deg/s, acceleration deg/s^2, status, time ms."""

    position_deg: float
    rate_deg_s: float
    accel_deg_s2: float
    status: int
    t_ms: int


def parse_read_all(line: str | bytes) -> ReadAll:
    r = parse_reply(line).split(",")
    if len(r) != 5:
        raise AclError(AclCode.COMMAND_ERROR, f"READ:ALL reply needs 5 fields, got {len(r)}")
    try:
        return ReadAll(float(r[0]), float(r[1]), float(r[2]), int(r[3], 16), int(r[4]))
    except ValueError as exc:
        raise AclError(AclCode.COMMAND_ERROR, f"bad READ:ALL reply: {exc}") from None


def parse_error_queue_entry(line: str | bytes) -> tuple[int, str]:
    """``-221,"Settings conflict"`` -> (-221, "Settings conflict")."""
    r = parse_reply(line)
    code, _, text = r.partition(",")
    try:
        return int(code), text.strip().strip('"')
    except ValueError:
        raise AclError(AclCode.COMMAND_ERROR, f"bad error-queue reply {r!r}") from None
