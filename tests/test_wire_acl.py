"""ACL-flavoured ASCII turntable protocol: the emulated server on a pty and TCP, and the driver's
resynchronisation against late replies (REALTIME_FILES; the parser and formatter without a
transport are in tests/test_acl_protocol.py)."""
from __future__ import annotations

import pytest
import serial

from rigctl.drivers import acl as A
from rigctl.drivers.modbus_map import StatusBit
from rigctl.sim.acl_server import AclServer, AclServerCore, IdealTable


@pytest.fixture
def server():
    srv = AclServer(IdealTable())
    yield srv
    srv.close()


def ask(port, line: bytes) -> str:
    port.write(line + b"\n")
    reply = port.readline()
    assert reply.endswith(b"\n"), f"no reply to {line!r}"
    return reply.decode().strip()


@pytest.mark.parametrize("transport", ["pty", "tcp"])
def test_session_over_real_transport(server, transport):
    if transport == "pty":
        url = server.open_pty()
    else:
        host, port = server.open_tcp()
        url = f"socket://{host}:{port}"
    p = serial.serial_for_url(url, baudrate=115200, timeout=2)
    try:
        assert ask(p, b"*IDN?").startswith("SIM,TT3-SIM,")
        assert ask(p, b":DEM:POS 1,10").startswith("ERR -221")           # interlock open
        assert ask(p, b":INT? 1") == "OPEN"
        assert ask(p, b":INTerlock:CLOSe ALL") == "OK"
        assert ask(p, b":MODE:POS 1;RATE 2\r") == "OK;OK"
        assert ask(p, b":MODE? 1") == "P" and ask(p, b":MODE? 2") == "R"
        assert ask(p, b":D:P 1,-135.5") == "OK"
        assert A.parse_float(ask(p, b":READ:POSITION? 1")) == pytest.approx(-135.5, abs=1e-6)
        assert A.parse_float(ask(p, b":DEM:POS? 1")) == pytest.approx(-135.5, abs=1e-6)
        st = A.parse_status(ask(p, b":STAT:AXIS? 1"))
        assert st & StatusBit.TARGET_REACHED and st & StatusBit.SERVO_ON and not st & StatusBit.INTERLOCK_OPEN
        assert ask(p, b":LIM:RATE R,2,50") == "OK"
        assert A.parse_float(ask(p, b":LIM:RATE? R,2")) == pytest.approx(50.0)
        assert ask(p, b":D:R 2,60").startswith("ERR -222")
        assert ask(p, b":D:R 2,20") == "OK"
        ra = A.parse_read_all(ask(p, b":READ:ALL? 2"))
        assert ra.rate_deg_s == pytest.approx(20.0) and ra.status & StatusBit.MOVING
        assert ask(p, b":S:E?").startswith("ERR -100")
        assert A.parse_error_queue_entry(ask(p, b":SYST:ERR?"))[0] == -221
        assert A.parse_error_queue_entry(ask(p, b":SYST:ERR?"))[0] == -222
        assert A.parse_error_queue_entry(ask(p, b":SYST:ERR?"))[0] == -100
        assert ask(p, b":SYST:ERR?") == '0,"No error"'
        assert ask(p, b":ABORT") == "OK"
        assert ask(p, b":MODE? 2") == "O" and A.parse_float(ask(p, b":READ:RATE? 2")) == 0.0
        assert ask(p, b":INT:OPEN 1") == "OK" and ask(p, b":INT? 1") == "OPEN"
    finally:
        p.close()


def test_interlock_trip_needs_reset(server):
    p = serial.serial_for_url(server.open_pty(), timeout=2)
    try:
        ask(p, b":INT:CLOSE 3")
        server.table.trip(3)
        assert ask(p, b":INT? 3") == "FAULT"
        assert A.parse_status(ask(p, b":STAT:AXIS? 3")) & StatusBit.FAULT
        assert ask(p, b":INT:CLOSE 3").startswith("ERR -221")
        assert ask(p, b":INT:RES") == "OK"
        assert ask(p, b":INT:CLOSE 3") == "OK" and ask(p, b":INT? 3") == "CLOSED"
    finally:
        p.close()


def test_dropped_and_garbled_replies_side_channel(server):
    host, port = server.open_tcp()
    p = serial.serial_for_url(f"socket://{host}:{port}", timeout=0.3)
    try:
        server.core.drop_replies = 1
        p.write(b"*IDN?\n")
        assert p.readline() == b""                           # the client sees a timeout
        # the replies that do come may take longer than 0.3 s on a loaded host: wait for them
        # (with 0.3 s, a late one read as 'no reply' or a partial line)
        p.timeout = 5
        server.core.garble_replies = 1
        with pytest.raises(A.AclError):
            A.parse_ok(ask(p, b":INT:CLOSE 1"))
        assert ask(p, b":INT? 1") == "CLOSED"
    finally:
        p.close()


# -- the driver's resynchronisation against late replies (a scripted controller on a real pty) ----
class _HeldReplies:
    """The emulated controller's line handler (one reply line per request line) that holds back
    its next ``hold`` replies: they go out together, just before the reply to the next request
    line -- as a controller that stalled and then caught up sends them, and after the driver
    drained its port for that request. ``lines``: the request lines received."""

    def __init__(self, core: AclServerCore) -> None:
        self.core, self.buf, self.hold = core, b"", 0
        self.held: list[str] = []
        self.lines: list[str] = []

    def __call__(self, data: bytes, write) -> None:
        self.buf += data
        *lines, self.buf = self.buf.split(b"\n")
        for line in lines:
            self.lines.append(line.decode("ascii"))
            reply = self.core.handle_line(line) + "\n"
            if self.hold:
                self.hold -= 1
                self.held.append(reply)
                continue
            write(("".join(self.held) + reply).encode("ascii"))
            self.held.clear()


@pytest.fixture
def scripted_pty():
    from rigctl.sim.links import PtyEndpoint

    handler = _HeldReplies(AclServerCore(IdealTable()))
    ep = PtyEndpoint(handler, name="acl-scripted")
    try:
        yield handler, ep.path
    finally:
        ep.close()


def _acl_table(path: str, timeout_s: float):
    from rigctl.clock import ScaledClock
    from rigctl.config.config import TableLimits
    from rigctl.drivers.acl_table import AclTable

    import numpy as np

    limits = TableLimits(rate=np.radians([100.0] * 3), accel=np.radians([100.0] * 3),
                         angle_min=np.full(3, -np.inf), angle_max=np.full(3, np.inf))
    return AclTable(path, limits, ScaledClock(1.0), timeout_s=timeout_s)


#: the reply timeout of the driver, wall s, where a reply must come (from the pty's thread, on a
#: loaded host); where the controller holds its replies, the timeout passes whatever it is
REPLY_S = 2.0
HELD_S = 0.2


def test_resync_does_not_take_a_late_idn_reply_for_its_own(scripted_pty):
    """A read times out and so does the resync of its retry (the controller holds both replies);
    the next read's resync then meets, after its drain, the late READ:ALL reply and the late
    ``*IDN?`` reply ahead of the reply to its own query. It must match only its own: the resync
    that took the late ``*IDN?`` reply left its own reply to be read as the READ:ALL answer (a
    bad reply, counted, and a third resync)."""
    from rigctl.drivers.serial_link import ReplyTimeout

    handler, path = scripted_pty
    table = _acl_table(path, REPLY_S)
    table.connect()
    try:
        handler.hold, table.timeout_s = 2, HELD_S
        with pytest.raises(ReplyTimeout):
            table.read()
        assert table.counters.timeouts == 2 and len(handler.held) == 2
        assert handler.held[1] == handler.core.idn + "\n"        # the resync's *IDN? reply, late
        table.timeout_s = REPLY_S
        state = table.read()
        assert not handler.held                                  # the late replies went out
        assert len(state.status) == 3 and state.angle.shape == (3,)
        assert table.counters.bad_replies == 0 and table.counters.resyncs == 2
        table.read()                                             # nothing left over to misread
        assert table.counters.bad_replies == 0 and table.counters.resyncs == 2
    finally:
        table.close()


def test_identify_retry_does_not_leave_a_late_idn_reply(scripted_pty):
    """The first ``*IDN?`` of the connect is answered late, just before the reply to the retry:
    the retry must take its own reply, not the late one (which left the retry's reply to be read
    as the answer to ``*CLS``: 'expected OK')."""
    handler, path = scripted_pty
    handler.hold = 1
    table = _acl_table(path, REPLY_S)
    try:
        table.connect()
        assert table.idn == handler.core.idn
        assert table.counters.timeouts == 1 and table.counters.bad_replies == 0
        assert len(table.read().status) == 3
    finally:
        table.close()
