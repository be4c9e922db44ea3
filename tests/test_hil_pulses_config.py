"""GPIO / modem-line pulse drivers (real gpiod and pyserial objects, no hardware), wired configs,
and `rigctl sim up` as a separate process."""
from __future__ import annotations

import os
import signal
import subprocess
import time
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest

from rigctl.clock import ScaledClock
from rigctl.config.config import load_config
from rigctl.drivers.modem_pulses import ModemPulses, parse_icount
from rigctl.yamlio import InputError

from helpers import ROOT, rigctl_cmd



class FakeRequest:
    """Imitates gpiod.LineRequest's wait_edge_events / read_edge_events / release, serving
    real gpiod.EdgeEvent objects."""

    def __init__(self, events: list) -> None:
        self.events, self.released = list(events), False

    def wait_edge_events(self, timeout: timedelta | float | None = None) -> bool:
        if self.events:
            return True
        time.sleep(0.01)
        return False

    def read_edge_events(self, max_events: int | None = None) -> list:
        out, self.events = self.events[:2], self.events[2:]
        return out

    def release(self) -> None:
        self.released = True


def test_gpio_edges_sequence_gaps_and_time_base():
    gpiod = pytest.importorskip("gpiod")           # optional extra 'gpio'
    from gpiod.line import Bias, Clock, Edge

    from rigctl.drivers.gpio_pulses import GpioPulses
    rising = gpiod.EdgeEvent.Type.RISING_EDGE.value
    t0 = time.monotonic_ns()
    events = [gpiod.EdgeEvent(rising, t0 + 1_000_000, 17, 1, 1), gpiod.EdgeEvent(rising, t0 + 2_000_000, 17, 2, 2),
              gpiod.EdgeEvent(rising, t0 + 5_000_000, 17, 5, 5),     # seqno 3, 4 lost
              gpiod.EdgeEvent(rising, t0 + 6_000_000, 4, 6, 1),      # another line
              gpiod.EdgeEvent(rising, t0 + 7_000_000, 17, 7, 5)]     # repeated seqno
    seen = {}

    def request_lines(path, config, consumer):
        seen.update(path=path, config=config, consumer=consumer)
        return FakeRequest(events)
    clock = ScaledClock(1.0)
    p = GpioPulses("/dev/gpiochip0", 17, clock, edge="rising", debounce_us=500, bias="pull-up",
                   request_lines=request_lines)
    p.connect()
    try:
        settings = seen["config"][17]
        assert isinstance(settings, gpiod.LineSettings)
        assert settings.edge_detection == Edge.RISING and settings.bias == Bias.PULL_UP
        assert settings.event_clock == Clock.MONOTONIC and settings.debounce_period == timedelta(microseconds=500)
        deadline, got = time.monotonic() + 2, []
        while sum(map(len, got)) < 3 and time.monotonic() < deadline:
            time.sleep(0.02)
            got.append(p.read())
        t = np.concatenate([g.time for g in got])
        assert len(t) == 3 and p.missed == 2 and p.foreign == 1 and p.out_of_order == 1
        np.testing.assert_allclose(np.diff(t), [1e-3, 3e-3], atol=1e-9)
        assert all(g.source == "gpio" for g in got)
    finally:
        p.close()


def test_gpio_missing_chip_is_a_clear_error():
    pytest.importorskip("gpiod")
    from rigctl.drivers.gpio_pulses import GpioPulses
    p = GpioPulses("/dev/gpiochip-none", 3, ScaledClock(1.0))
    with pytest.raises(RuntimeError, match="cannot request line 3 of /dev/gpiochip-none"):
        p.connect()


def test_modem_wait_mode_on_a_pty_is_a_clear_error():
    master, slave = os.openpty()
    try:
        p = ModemPulses(os.ttyname(slave), ScaledClock(1.0), mode="wait")
        with pytest.raises(RuntimeError, match="no modem-status lines"):
            p.connect()
    finally:
        os.close(master)
        os.close(slave)


def test_modem_poll_mode_sees_cts_edges_on_pyserial_loop():
    p = ModemPulses("loop://", ScaledClock(1.0), line="cts", edge="rising", mode="poll", poll_interval_s=0.001)
    p.connect()
    try:
        p.ser.rts = False                      # pyserial opens with RTS asserted
        time.sleep(0.02)
        for _ in range(3):                     # loop:// mirrors RTS onto CTS
            p.ser.rts = True
            time.sleep(0.02)
            p.ser.rts = False
            time.sleep(0.02)
        pulses = p.read()
        assert len(pulses) == 3 and p.edges == 3 and pulses.source == "modem"
        assert np.all(np.diff(pulses.time) > 0.03)
    finally:
        p.close()


def test_modem_icount_parsing_and_missed_edges():
    import array
    buf = array.array("i", [5, 6, 7, 8] + [0] * 16).tobytes()
    assert parse_icount(buf) == {"cts": 5, "dsr": 6, "ri": 7, "cd": 8}
    p = ModemPulses("loop://", ScaledClock(1.0), line="cd")
    p._level, p._host0, p._run0, p.speed = False, 0, 0.0, 1.0
    p.on_change(1_000_000, True, 1)            # clean rising edge
    p.on_change(2_000_000, True, 2)            # level unchanged but two transitions: a lost pulse
    assert p.edges == 1 and p.missed == 2


def test_wired_config_errors_name_the_line(tmp_path):
    with pytest.raises(InputError, match=r"sim-wire.yaml:\d+: 'port: auto'"):
        load_config(ROOT / "configs" / "sim-wire.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("table:\n  driver: modbus\n  transport: tcp\nimu:\n  driver: xsens\n  port: /dev/null\n")
    with pytest.raises(InputError, match="Modbus TCP needs 'host'"):
        load_config(bad)
    bad.write_text("clock: virtual\ntable:\n  driver: acl\n  port: /dev/null\nimu:\n  driver: xsens\n  port: /dev/null\n")
    with pytest.raises(InputError, match="virtual time cannot drive wired devices"):
        load_config(bad)


def test_example_lab_config_loads():
    cfg = load_config(ROOT / "configs" / "example-lab.yaml")
    assert cfg.table.driver == "acl" and cfg.table.settings.port == "/dev/ttyUSB0"
    assert cfg.imu.settings.baudrate == 921_600 and cfg.pulses.driver == "novatel"
    assert cfg.clock == "real"


def test_sim_up_cli_serves_a_wired_run(tmp_path):
    wired = tmp_path / "wired.yaml"
    proc = subprocess.Popen([*rigctl_cmd(), "sim", "up", "--speed", "100", "--wire-config", str(wired),
                             "--link-dir", str(tmp_path / "ports")], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        lines = []
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            lines.append(line)
            if line.strip() == "ready" or not line:
                break
        assert lines[-1].strip() == "ready", "".join(lines)
        text = "".join(lines)
        assert "imu_xsens_pty" in text and "table_modbus_tcp" in text and str(wired) in text
        assert (tmp_path / "ports" / "imu").is_symlink()
        run = subprocess.run([*rigctl_cmd(), "run", str(ROOT / "procedures" / "rates.yaml"), "--config", str(wired),
                              "-p", "revolutions=1", "--out", str(tmp_path / "runs")], cwd=ROOT,
                             capture_output=True, text=True, timeout=120)
        assert run.returncode == 0, run.stdout + run.stderr
        assert "18 segments" in run.stdout + run.stderr
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0 and "stopped" in out
    assert not (tmp_path / "ports" / "imu").exists()
