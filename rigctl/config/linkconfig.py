"""Connection settings of wired devices (the ``table``, ``imu`` and ``pulses`` sections of a rig
config), validated at load time so a typo names its file and line before anything is opened.

Every serial-style ``port`` is a pyserial URL: a device path (``/dev/ttyUSB0``, a pty or a symlink
to one), ``socket://host:port`` (raw TCP, e.g. a serial-device server or ``rigctl sim up``),
``rfc2217://host:port`` or ``spy:///dev/ttyUSB0`` (traffic dump). ``port: auto`` is the placeholder
of configs/sim-wire.yaml that ``rigctl sim up --wire-config OUT.yaml`` fills in.

One frozen dataclass per driver (:class:`AclSettings`, :class:`ModbusSettings`,
:class:`XsensSettings`, :class:`NovatelSettings`, :class:`GpioSettings`, :class:`ModemSettings`)
names each setting once, with its default and its range; :func:`parse` is the one validator
(unknown keys with "did you mean", types, ranges and choices, each error with file and line);
rig.py passes :meth:`LinkSettings.keywords` to the driver, whose keyword arguments carry the same
names (tests/test_link_settings.py checks that they agree).

Per driver (units in the key names; defaults in brackets):

* table ``acl``: port, baudrate [115200], timeout_s [0.5], close_interlocks [true],
  open_interlocks_on_stop [false]
* table ``modbus``: transport tcp|rtu [tcp]; tcp: host, tcp_port [502]; rtu: port, baudrate
  [19200], parity N|E|O [N]; unit_id [1], word_order big|little [big], timeout_s [0.5],
  retries [1], watchdog_ms [0 = off], window_deg, dwell_s (controller in-position criterion;
  unset = keep the controller's)
* imu ``xsens``: port, baudrate [921600], rate_hz (top level of the section), timeout_s [0.5],
  sample_time_fine_wrap [4294967296; 864000000 for MTi-10/100], align_wait_s [0.02],
  link_timeout_s [2.0]; serial (any IMU driver: the unit's label, rigctl.config.config.imu_serial)
* imu ``vectornav``: port, baudrate [921600], rate_hz (800 Hz / N), timeout_s [0.5], align_wait_s
  [0.02], link_timeout_s [2.0]; serial
* imu ``frame``: port, baudrate [115200], rate_hz, timeout_s [0.5], align_wait_s [0.02],
  link_timeout_s [2.0], frame (the frame description, rigctl.config.frame_spec); serial
* pulses ``novatel``: port, baudrate [115200], signal MARK1..MARK4 [MARK1], polarity
  NEGATIVE|POSITIVE [NEGATIVE], timebias_ns [0], timeguard_ms [4], log MARK1TIMEA|MARKTIMEA
* pulses ``gpio``: chip [/dev/gpiochip0], line, edge rising|falling|both [rising],
  event_clock monotonic|realtime|hte [monotonic], debounce_us [0], bias as-is|pull-up|pull-down
* pulses ``modem``: port, line cd|cts|dsr|ri [cd], edge rising|falling|both [rising],
  mode wait|poll [wait], poll_interval_s [0.001]
"""
from __future__ import annotations

from dataclasses import MISSING, dataclass, fields
from typing import Any, ClassVar

from .. import schema as S
from .. import settings
from ..settings import Settings, flag, number, setting, text
from .frame_spec import parse_frame_spec
from ..yamlio import LocDict

AUTO = "auto"
#: keys every device section may carry besides its link settings
COMMON_KEYS = ("driver", "sim", "limits", "rate_hz")


def port(required: bool = True) -> Any:
    return setting(MISSING if required else None, read=_port)


def baudrate(default: int) -> Any:
    return number(default, minimum=50, maximum=20_000_000, integer=True)


def timeout(default: float = 0.5) -> Any:
    return number(default, minimum=0.001, maximum=60)


EDGES = ("rising", "falling", "both")


@dataclass(frozen=True, kw_only=True)
class LinkSettings(Settings):
    """Base of the settings of one wired driver (a section of the rig config)."""

    #: the driver's name in the config; the fields the driver takes as positional arguments
    DRIVER: ClassVar[str] = ""
    POSITIONAL: ClassVar[tuple[str, ...]] = ("port",)

    def keywords(self) -> dict[str, Any]:
        """The driver's keyword arguments (every field but :attr:`POSITIONAL`)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in self.POSITIONAL}

    def where(self) -> str:
        """Where the device is, as one line names it."""
        return str(getattr(self, "port", ""))


def _port(d: LocDict, key: str, default: Any = None) -> str:
    value = S.get_str(d, key)
    if not value.strip():
        raise S.error(d, key, f"'{key}' is empty", "give a device path or a pyserial URL")
    if value == AUTO:
        raise S.error(d, key, f"'{key}: auto' ({d.get('driver', '?')}) is a placeholder filled in by the "
                      "emulator", "start `rigctl sim up --wire-config OUT.yaml` and use OUT.yaml")
    return value


def parse(cls: type[LinkSettings], d: LocDict, what: str) -> LinkSettings:
    """The one validator (rigctl.settings.parse), with the keys every device section may carry."""
    return settings.parse(cls, d, what, COMMON_KEYS)


@dataclass(frozen=True, kw_only=True)
class AclSettings(LinkSettings):
    """table ``acl`` (rigctl.drivers.acl_table.AclTable)."""

    DRIVER: ClassVar[str] = "acl"
    port: str = port()
    baudrate: int = baudrate(115200)
    timeout_s: float = timeout()
    close_interlocks: bool = flag(True)
    open_interlocks_on_stop: bool = flag(False)


@dataclass(frozen=True, kw_only=True)
class ModbusSettings(LinkSettings):
    """table ``modbus`` (rigctl.drivers.modbus_table.ModbusTable): TCP (host, tcp_port) or RTU
    (port, baudrate, parity)."""

    DRIVER: ClassVar[str] = "modbus"
    POSITIONAL: ClassVar[tuple[str, ...]] = ()
    transport: str = text("tcp", choices=("tcp", "rtu"))
    host: str | None = text(None)
    tcp_port: int = number(502, minimum=1, maximum=65535, integer=True)
    port: str | None = port(required=False)
    baudrate: int = baudrate(19200)
    parity: str = text("N", choices=("N", "E", "O"))
    unit_id: int = number(1, minimum=0, maximum=247, integer=True)
    word_order: str = text("big", choices=("big", "little"))
    timeout_s: float = timeout()
    retries: int = number(1, minimum=0, maximum=10, integer=True)
    watchdog_ms: int = number(0, minimum=0, maximum=65535, integer=True)
    window_deg: float | None = number(None, minimum=0, maximum=10, allow_none=True)
    dwell_s: float | None = number(None, minimum=0, maximum=65.535, allow_none=True)

    def check(self, d: LocDict) -> None:
        if self.transport == "tcp" and self.host is None:
            raise S.error(d, None, "Modbus TCP needs 'host'", "e.g. host: 192.168.0.10 (tcp_port: 502)")
        if self.transport == "rtu" and self.port is None:
            raise S.error(d, None, "'table' (modbus) is missing 'port'", "add a line 'port: ...'")

    def where(self) -> str:
        return f"{self.host}:{self.tcp_port}" if self.transport == "tcp" else str(self.port)


@dataclass(frozen=True, kw_only=True)
class XsensSettings(LinkSettings):
    """imu ``xsens`` (rigctl.drivers.xsens_imu.XsensImu; rate_hz is the section's own)."""

    DRIVER: ClassVar[str] = "xsens"
    EXTRA_KEYS: ClassVar[tuple[str, ...]] = ("serial",)
    port: str = port()
    baudrate: int = baudrate(921600)
    timeout_s: float = timeout()
    sample_time_fine_wrap: int = number(1 << 32, minimum=1000, maximum=1 << 32, integer=True)
    align_wait_s: float = number(0.02, minimum=0, maximum=1)
    link_timeout_s: float = number(2.0, minimum=0.01, maximum=600)


@dataclass(frozen=True, kw_only=True)
class VectorNavSettings(LinkSettings):
    """imu ``vectornav`` (rigctl.drivers.vectornav_imu.VectorNavImu; rate_hz is the section's
    own and must be 800 Hz / N)."""

    DRIVER: ClassVar[str] = "vectornav"
    EXTRA_KEYS: ClassVar[tuple[str, ...]] = ("serial",)
    port: str = port()
    baudrate: int = baudrate(921600)
    timeout_s: float = timeout()
    align_wait_s: float = number(0.02, minimum=0, maximum=1)
    link_timeout_s: float = number(2.0, minimum=0.01, maximum=600)

    def check(self, d: LocDict) -> None:
        rate = d.get("rate_hz", 100.0)
        if isinstance(rate, (int, float)) and rate > 0 and (800.0 / rate) != int(800.0 / rate):
            raise S.error(d, "rate_hz", f"a VectorNav outputs at 800 Hz / N; rate_hz {rate:g} is not one of those",
                          "e.g. rate_hz: 100 (800 / 8), 200, 400 or 800")


@dataclass(frozen=True, kw_only=True)
class FrameSettings(LinkSettings):
    """imu ``frame`` (rigctl.drivers.frame_imu.FrameImu): a declarative frame description under
    ``frame:`` (rigctl.config.frame_spec), checked here with file and line."""

    DRIVER: ClassVar[str] = "frame"
    EXTRA_KEYS: ClassVar[tuple[str, ...]] = ("serial", "frame")
    port: str = port()
    baudrate: int = baudrate(115200)
    timeout_s: float = timeout()
    align_wait_s: float = number(0.02, minimum=0, maximum=1)
    link_timeout_s: float = number(2.0, minimum=0.01, maximum=600)

    def check(self, d: LocDict) -> None:
        spec = parse_frame_spec(d)
        rate = d.get("rate_hz", 100.0)
        if spec.format == "binary" and isinstance(rate, (int, float)) and 10 * spec.length * rate > self.baudrate:
            raise S.error(d, "baudrate", f"{spec.length}-byte frames at {rate:g} Hz need "
                          f"{10 * spec.length * rate:,.0f} bit/s, more than baudrate {self.baudrate:,}",
                          "raise the baud rate (as the IMU is set) or lower rate_hz")


@dataclass(frozen=True, kw_only=True)
class NovatelSettings(LinkSettings):
    """pulses ``novatel`` (rigctl.drivers.novatel_marks.NovatelMarks)."""

    DRIVER: ClassVar[str] = "novatel"
    port: str = port()
    baudrate: int = baudrate(115200)
    timeout_s: float = timeout(1.0)
    signal: str = text("MARK1", choices=("MARK1", "MARK2", "MARK3", "MARK4"))
    polarity: str = text("NEGATIVE", choices=("NEGATIVE", "POSITIVE"))
    timebias_ns: int = number(0, minimum=-10**9, maximum=10**9, integer=True)
    timeguard_ms: int = number(4, minimum=4, maximum=3_599_999, integer=True)
    log_name: str = text("MARK1TIMEA", key="log", choices=("MARK1TIMEA", "MARKTIMEA"))


@dataclass(frozen=True, kw_only=True)
class GpioSettings(LinkSettings):
    """pulses ``gpio`` (rigctl.drivers.gpio_pulses.GpioPulses)."""

    DRIVER: ClassVar[str] = "gpio"
    POSITIONAL: ClassVar[tuple[str, ...]] = ("chip", "line")
    chip: str = text("/dev/gpiochip0")
    line: int = number(minimum=0, maximum=65535, integer=True)
    edge: str = text("rising", choices=EDGES)
    event_clock: str = text("monotonic", choices=("monotonic", "realtime", "hte"))
    debounce_us: int = number(0, minimum=0, maximum=10**6, integer=True)
    bias: str = text("as-is", choices=("as-is", "pull-up", "pull-down", "disabled"))

    def where(self) -> str:
        return f"{self.chip} line {self.line}"


@dataclass(frozen=True, kw_only=True)
class ModemSettings(LinkSettings):
    """pulses ``modem`` (rigctl.drivers.modem_pulses.ModemPulses)."""

    DRIVER: ClassVar[str] = "modem"
    port: str = port()
    baudrate: int = baudrate(9600)
    line: str = text("cd", choices=("cd", "cts", "dsr", "ri"))
    edge: str = text("rising", choices=EDGES)
    mode: str = text("wait", choices=("wait", "poll"))
    poll_interval_s: float = number(0.001, minimum=1e-4, maximum=1)


#: (section, driver) -> its settings
SETTINGS: dict[tuple[str, str], type[LinkSettings]] = {
    ("table", "acl"): AclSettings, ("table", "modbus"): ModbusSettings, ("imu", "xsens"): XsensSettings,
    ("imu", "vectornav"): VectorNavSettings, ("imu", "frame"): FrameSettings,
    ("pulses", "novatel"): NovatelSettings, ("pulses", "gpio"): GpioSettings, ("pulses", "modem"): ModemSettings,
}


def link_settings(section: str, driver: str, d: LocDict) -> LinkSettings | None:
    """The validated settings of a wired driver; None for the emulator (``sim``) or ``none``."""
    cls = SETTINGS.get((section, driver))
    return None if cls is None else parse(cls, d, f"'{section}' ({driver})")
