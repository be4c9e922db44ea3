"""ACL-flavoured ASCII turntable protocol without a transport: the parser, the formatter, the
emulated server's core on random bytes and the ideal table's rate (no wall-clock deadline: any
worker; the server on a pty and TCP is in tests/test_wire_acl.py, REALTIME_FILES)."""
from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rigctl.drivers import acl as A
from rigctl.drivers.modbus_map import StatusBit
from rigctl.sim.acl_server import AclServerCore, IdealTable


def test_abbreviations_resolve_to_canonical_paths():
    assert A.parse_message(":M:P 1") == [A.AclRequest(("MODE", "POSITION"), False, ("1",))]
    assert A.parse_message(":d:r 2,10.5") == [A.AclRequest(("DEMAND", "RATE"), False, ("2", "10.5"))]
    assert A.parse_message(":R:P? 1")[0].path == ("READ", "POSITION")
    assert A.parse_message("interlock:close ALL")[0].path == ("INTERLOCK", "CLOSE")
    assert A.parse_message(":READ:POS 3")[0].query is True          # '?' optional for READ
    assert A.parse_message("*idn?") == [A.AclRequest(("*IDN",), True)]


def test_chained_commands_stay_in_subsystem():
    reqs = A.parse_message(":Mode:Position 1;Rate 2;:DEM:POS 1,5")
    assert [r.path for r in reqs] == [("MODE", "POSITION"), ("MODE", "RATE"), ("DEMAND", "POSITION")]
    assert [r.args for r in reqs] == [("1",), ("2",), ("1", "5")]


@pytest.mark.parametrize("bad", [":S:E?", ":FOO 1", ":MODE:POSITION? 1", ":READ:BANANA? 1", "*XYZ", "",
                                 ":ABORT?", "\xff"])
def test_bad_commands_raise_command_error(bad):
    with pytest.raises(A.AclError) as e:
        A.parse_message(bad.encode("latin-1"))
    assert e.value.code == A.AclCode.COMMAND_ERROR


@settings(max_examples=200, deadline=None, derandomize=True, database=None)
@given(st.binary(max_size=60))
def test_server_core_never_crashes_on_random_input(data):
    core = AclServerCore(IdealTable())
    reply = core.handle_line(data)
    assert reply is not None and "\n" not in reply


def test_driver_side_formatting_and_reply_parsing():
    assert A.command(":DEMAND:POSITION", 1, 90.0) == b":DEMAND:POSITION 1,90.000000\n"
    assert A.query(":READ:POSITION", 2) == b":READ:POSITION? 2\n"
    assert A.query("*IDN") == b"*IDN?\n"
    assert A.parse_float(b"12.500000\n") == 12.5
    assert A.parse_status("0x0507") == 0x0507
    ra = A.parse_read_all(A.format_read_all(1.5, -2.0, 0.25, 0x0107, 1234))
    assert ra == A.ReadAll(1.5, -2.0, 0.25, 0x0107, 1234)
    assert A.parse_error_queue_entry('-221,"interlock open"') == (-221, "interlock open")
    with pytest.raises(A.AclError) as e:
        A.parse_reply("ERR -222,rate above limit")
    assert (e.value.code, e.value.text) == (-222, "rate above limit")
    A.parse_ok("OK\r\n")
    with pytest.raises(A.AclError):
        A.parse_ok("P")


def test_ideal_table_rate_integrates_angle():
    t = [0.0]
    table = IdealTable(clock=lambda: t[0])
    table.interlock_close(1)
    table.set_mode(1, "rate")
    table.set_rate(1, math.radians(10.0))
    t[0] = 2.5
    r = table.read(1)
    assert r["angle"] == pytest.approx(math.radians(25.0))
    assert r["status"] & StatusBit.AT_RATE
