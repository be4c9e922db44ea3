"""The wired drivers' settings (rigctl.config.linkconfig): one dataclass per driver, one validator, and
the driver's own keyword arguments agreeing with them (names and defaults)."""
from __future__ import annotations

import dataclasses
import inspect
from pathlib import Path

import pytest

from rigctl.config.config import load_config
from rigctl.drivers.acl_table import AclTable
from rigctl.drivers.gpio_pulses import GpioPulses
from rigctl.drivers.modbus_table import ModbusTable
from rigctl.drivers.modem_pulses import ModemPulses
from rigctl.drivers.novatel_marks import NovatelMarks
from rigctl.drivers.frame_imu import FrameImu
from rigctl.drivers.vectornav_imu import VectorNavImu
from rigctl.drivers.xsens_imu import XsensImu
from rigctl.errors import InputError
from rigctl.config.linkconfig import (SETTINGS, AclSettings, FrameSettings, GpioSettings, ModbusSettings,
    ModemSettings, NovatelSettings, VectorNavSettings, XsensSettings)

DRIVERS = {AclSettings: AclTable, ModbusSettings: ModbusTable, XsensSettings: XsensImu,
           VectorNavSettings: VectorNavImu, FrameSettings: FrameImu,
           NovatelSettings: NovatelMarks, GpioSettings: GpioPulses, ModemSettings: ModemPulses}
#: the first positional parameter name of each driver that takes the port (or chip) first
FIRST = {AclTable: "url", XsensImu: "url", VectorNavImu: "url", FrameImu: "url", NovatelMarks: "url", ModemPulses: "url", GpioPulses: "chip"}


def test_every_wired_driver_has_one_settings_class() -> None:
    assert set(SETTINGS.values()) == set(DRIVERS)


@pytest.mark.parametrize("cls", list(DRIVERS), ids=lambda c: c.__name__)
def test_the_settings_are_the_drivers_keyword_arguments(cls) -> None:
    """Each keyword the config passes is a keyword-only parameter of the driver, with the same
    default: a setting renamed or re-defaulted on one side only fails here."""
    params = inspect.signature(DRIVERS[cls].__init__).parameters
    for f in dataclasses.fields(cls):
        if f.name in cls.POSITIONAL:
            continue
        p = params.get(f.name)
        assert p is not None and p.kind is inspect.Parameter.KEYWORD_ONLY, (cls.__name__, f.name)
        if f.default is not dataclasses.MISSING:
            assert p.default == f.default, (cls.__name__, f.name, p.default, f.default)
    positional = [n for n, p in params.items() if p.kind is inspect.Parameter.POSITIONAL_OR_KEYWORD][1:]
    if DRIVERS[cls] in FIRST:
        assert positional[0] == FIRST[DRIVERS[cls]]
    assert len(cls.POSITIONAL) <= len(positional)


def _config(tmp_path: Path, pulses: str) -> Path:
    p = tmp_path / "rig.yaml"
    p.write_text("clock: real\ntable:\n  driver: acl\n  port: /dev/null\nimu:\n  driver: xsens\n"
                 f"  port: /dev/null\npulses:\n{pulses}")
    return p


def test_values_defaults_and_the_yaml_key_of_a_renamed_field(tmp_path: Path) -> None:
    cfg = load_config(_config(tmp_path, "  driver: novatel\n  port: /dev/ttyS1\n  log: MARKTIMEA\n"
                                        "  timebias_ns: -250\n"))
    s = cfg.pulses.settings
    assert isinstance(s, NovatelSettings)
    assert (s.port, s.log_name, s.timebias_ns, s.timeguard_ms, s.baudrate) == \
        ("/dev/ttyS1", "MARKTIMEA", -250, 4, 115200)
    assert s.keywords()["log_name"] == "MARKTIMEA" and "port" not in s.keywords()
    assert cfg.table.settings == AclSettings(port="/dev/null")
    g = load_config(_config(tmp_path, "  driver: gpio\n  line: 17\n  edge: both\n")).pulses.settings
    assert g == GpioSettings(line=17, edge="both") and g.where() == "/dev/gpiochip0 line 17"


@pytest.mark.parametrize("pulses, message, line", [
    ("  driver: modem\n  port: /dev/ttyS1\n  lien: cts\n", r"unknown key 'lien' in 'pulses' \(modem\) \(did you mean 'line'\?\)", 11),
    ("  driver: modem\n  port: /dev/ttyS1\n  edge: up\n", r"'edge' = 'up' is not allowed \(choose one of: rising, falling, both\)", 11),
    ("  driver: novatel\n  port: /dev/ttyS1\n  timeguard_ms: 2\n", r"'timeguard_ms' = 2 is below its minimum 4", 11),
    ("  driver: novatel\n  port: /dev/ttyS1\n  log: MARK9TIMEA\n", r"'log' = 'MARK9TIMEA' is not allowed", 11),
    ("  driver: gpio\n  edge: rising\n", r"'pulses' \(gpio\) is missing 'line'", 9),
    ("  driver: modem\n  port: ''\n", r"'port' is empty", 10),
])
def test_errors_name_file_line_and_what_to_do(tmp_path: Path, pulses: str, message: str, line: int) -> None:
    path = _config(tmp_path, pulses)
    with pytest.raises(InputError, match=message) as err:
        load_config(path)
    assert err.value.file == str(path) and err.value.line == line, str(err.value)


@pytest.mark.parametrize("extra, message, line", [
    ("site:\n  latitude_dg: 48\n", r"unknown key 'latitude_dg' in 'site' \(did you mean 'latitude_deg'\?\)", 3),
    ("site:\n  latitude_deg: 91\n", r"'latitude_deg' = 91 is above its maximum 90", 3),
    ("site:\n  gravity_m_s2: heavy\n", r"'gravity_m_s2'.*must be a number", 3),
    ("recorder:\n  flush_intervall_s: 0.2\n", r"unknown key 'flush_intervall_s' in 'recorder' \(did you mean 'flush_interval_s'\?\)", 3),
    ("recorder:\n  table_rate_hz: 0\n", r"'table_rate_hz' = 0 is below its minimum 0.1", 3),
    ("traceability:\n  laboratry: Inertial Lab\n",
     r"unknown key 'laboratry' in 'traceability' \(did you mean 'laboratory'\?\)", 3),
    ("traceability:\n  table_id: [1, 2]\n", r"'table_id' must be text", 3),
    ("suspenders:\n  hold_sec: 5\n", r"unknown key 'hold_sec' in 'suspenders' \(did you mean 'hold_s'\?\)", 3),
    ("notifications:\n  webhook:\n    ulr: http://127.0.0.1:9/x\n",
     r"unknown key 'ulr' in 'notifications.webhook' \(did you mean 'url'\?\)", 4),
    ("notifications:\n  email:\n    smtp_host: x\n    from: rig@lab\n    to: [a@b]\n    smtp_prot: 25\n",
     r"unknown key 'smtp_prot' in 'notifications.email' \(did you mean 'smtp_port'\?\)", 7),
])
def test_config_sections_are_typed_settings_with_the_same_errors(tmp_path: Path, extra: str, message: str,
                                                                     line: int) -> None:
    """site:, recorder:, suspenders: and notifications: (with its nested sections) go through
    the same validator as the link settings (rigctl.settings.parse): file, line and "did you
    mean" on every error."""
    path = tmp_path / "rig.yaml"
    path.write_text("clock: virtual\n" + extra + "table:\n  driver: sim\nimu:\n  driver: sim\n")
    with pytest.raises(InputError, match=message) as err:
        load_config(path)
    assert err.value.file == str(path) and err.value.line == line, str(err.value)
    ok = tmp_path / "ok.yaml"
    ok.write_text("site:\n  latitude_deg: 48\n  gravity_m_s2: 9.81\nrecorder:\n  table_rate_hz: 20\n"
                  "table:\n  driver: sim\nimu:\n  driver: sim\n")
    cfg = load_config(ok)
    assert cfg.gravity == 9.81 and abs(cfg.latitude - 0.837758041) < 1e-9 and cfg.table_rate_hz == 20


def test_the_chamber_settings_are_the_drivers_keyword_arguments() -> None:
    """Each chamber setting the rig passes (keywords(): all but band_c, the suspender's band) is
    a keyword of the driver with the same default; ``resource`` is the SCPI driver's first
    positional parameter."""
    from rigctl.config.chamber import ScpiChamberSettings, WatlowSettings
    from rigctl.drivers.scpi_chamber import ScpiChamber
    from rigctl.drivers.watlow_chamber import WatlowF4T

    for cls, drv, positional in ((WatlowSettings, WatlowF4T, ()), (ScpiChamberSettings, ScpiChamber, ("resource",))):
        params = inspect.signature(drv.__init__).parameters
        for f in dataclasses.fields(cls):
            if f.name == "band_c" or f.name in positional:
                continue
            p = params.get(f.name)
            assert p is not None and p.kind is inspect.Parameter.KEYWORD_ONLY, (cls.__name__, f.name)
            if f.default is not dataclasses.MISSING:
                assert p.default == f.default, (cls.__name__, f.name, p.default, f.default)
        for name in positional:
            assert params[name].kind is inspect.Parameter.POSITIONAL_OR_KEYWORD


@pytest.mark.parametrize("chamber, message, line", [
    ("  driver: watlow\n  port: /dev/ttyUSB3\n  trasnport: tcp\n",
     r"unknown key 'trasnport' in 'chamber' \(watlow\) \(did you mean 'transport'\?\)", 4),
    ("  driver: watlow\n  transport: rtu\n", r"'chamber' \(watlow\) is missing 'port'", 2),
    ("  driver: scpi\n  model: generic\n", r"'chamber' \(scpi\) is missing 'resource'", 2),
    ("  driver: sim\n  safe_c: 25\n  band_c: [30, 90]\n", r"band_c \[30, 90\] must contain safe_c 25 degC", 4),
])
def test_chamber_errors_name_file_line_and_what_to_do(tmp_path: Path, chamber: str, message: str, line: int) -> None:
    path = tmp_path / "rig.yaml"
    path.write_text("chamber:\n" + chamber + "table:\n  driver: sim\nimu:\n  driver: sim\n")
    with pytest.raises(InputError, match=message) as err:
        load_config(path)
    assert err.value.file == str(path) and err.value.line == line, str(err.value)
