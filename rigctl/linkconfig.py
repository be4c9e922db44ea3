"""Connection settings of wired devices (the ``table``, ``imu`` and ``pulses`` sections of a rig
config), validated at load time so a typo names its file and line before anything is opened.

Every serial-style ``port`` is a pyserial URL: a device path (``/dev/ttyUSB0``, a pty or a symlink
to one), ``socket://host:port`` (raw TCP, e.g. a serial-device server or ``rigctl sim up``),
``rfc2217://host:port`` or ``spy:///dev/ttyUSB0`` (traffic dump). ``port: auto`` is the placeholder
of configs/sim-wire.yaml that ``rigctl sim up --wire-config OUT.yaml`` fills in.

Per driver (units in the key names; defaults in brackets):

* table ``acl``: port, baudrate [115200], timeout_s [0.5], close_interlocks [true],
  open_interlocks_on_stop [false]
* table ``modbus``: transport tcp|rtu [tcp]; tcp: host, tcp_port [502]; rtu: port, baudrate
  [19200], parity N|E|O [N]; unit_id [1], word_order big|little [big], timeout_s [0.5],
  retries [1], watchdog_ms [0 = off], window_deg, dwell_s (controller in-position criterion;
  unset = keep the controller's)
* imu ``xsens``: port, baudrate [921600], rate_hz (top level of the section), timeout_s [0.5],
  sample_time_fine_wrap [4294967296; 864000000 for MTi-10/100], align_wait_s [0.02],
  link_timeout_s [2.0]; serial (any IMU driver: the unit's label, rigctl.config.imu_serial)
* pulses ``novatel``: port, baudrate [115200], signal MARK1..MARK4 [MARK1], polarity
  NEGATIVE|POSITIVE [NEGATIVE], timebias_ns [0], timeguard_ms [4], log MARK1TIMEA|MARKTIMEA
* pulses ``gpio``: chip [/dev/gpiochip0], line, edge rising|falling|both [rising],
  event_clock monotonic|realtime|hte [monotonic], debounce_us [0], bias as-is|pull-up|pull-down
* pulses ``modem``: port, line cd|cts|dsr|ri [cd], edge rising|falling|both [rising],
  mode wait|poll [wait], poll_interval_s [0.001]
"""
from __future__ import annotations

from typing import Any

from . import schema as S
from .yamlio import LocDict

AUTO = "auto"
#: keys every device section may carry besides its link settings
COMMON_KEYS = ("driver", "sim", "limits", "rate_hz")


def _port(d: LocDict, driver: str, required: bool = True) -> str | None:
    if "port" not in d and not required:
        return None
    port = S.get_str(d, "port")
    if not port.strip():
        raise S.error(d, "port", "'port' is empty", "give a device path or a pyserial URL")
    if port == AUTO:
        raise S.error(d, "port", f"'port: auto' ({driver}) is a placeholder filled in by the emulator",
                      "start `rigctl sim up --wire-config OUT.yaml` and use OUT.yaml")
    return port


def _baud(d: LocDict, default: int) -> int:
    return int(S.get_number(d, "baudrate", default, minimum=50, maximum=20_000_000, integer=True))


def _timeout(d: LocDict, default: float = 0.5) -> float:
    return float(S.get_number(d, "timeout_s", default, minimum=0.001, maximum=60))


def table_settings(driver: str, d: LocDict) -> dict[str, Any]:
    if driver == "sim":
        return {}
    if driver == "acl":
        S.check_keys(d, (*COMMON_KEYS, "port", "baudrate", "timeout_s", "close_interlocks",
                         "open_interlocks_on_stop"), "'table' (acl)")
        return {"port": _port(d, driver), "baudrate": _baud(d, 115200), "timeout_s": _timeout(d),
                "close_interlocks": S.get_bool(d, "close_interlocks", True),
                "open_interlocks_on_stop": S.get_bool(d, "open_interlocks_on_stop", False)}
    S.check_keys(d, (*COMMON_KEYS, "transport", "host", "tcp_port", "port", "baudrate", "parity",
                     "unit_id", "word_order", "timeout_s", "retries", "watchdog_ms", "window_deg",
                     "dwell_s"), "'table' (modbus)")
    transport = S.get_str(d, "transport", "tcp", choices=("tcp", "rtu"))
    out: dict[str, Any] = {"transport": transport, "timeout_s": _timeout(d),
                           "unit_id": int(S.get_number(d, "unit_id", 1, minimum=0, maximum=247, integer=True)),
                           "word_order": S.get_str(d, "word_order", "big", choices=("big", "little")),
                           "retries": int(S.get_number(d, "retries", 1, minimum=0, maximum=10, integer=True)),
                           "watchdog_ms": int(S.get_number(d, "watchdog_ms", 0, minimum=0, maximum=65535,
                                                           integer=True)),
                           "window_deg": S.get_number(d, "window_deg", None, minimum=0, maximum=10,
                                                      allow_none=True),
                           "dwell_s": S.get_number(d, "dwell_s", None, minimum=0, maximum=65.535,
                                                   allow_none=True)}
    if transport == "tcp":
        if "host" not in d:
            raise S.error(d, None, "Modbus TCP needs 'host'", "e.g. host: 192.168.0.10 (tcp_port: 502)")
        out.update(host=S.get_str(d, "host"),
                   tcp_port=int(S.get_number(d, "tcp_port", 502, minimum=1, maximum=65535, integer=True)))
    else:
        out.update(port=_port(d, driver), baudrate=_baud(d, 19200),
                   parity=S.get_str(d, "parity", "N", choices=("N", "E", "O")))
    return out


def imu_settings(driver: str, d: LocDict) -> dict[str, Any]:
    if driver == "sim":
        return {}
    S.check_keys(d, (*COMMON_KEYS, "serial", "port", "baudrate", "timeout_s", "sample_time_fine_wrap",
                     "align_wait_s", "link_timeout_s"), "'imu' (xsens)")
    return {"port": _port(d, driver), "baudrate": _baud(d, 921600), "timeout_s": _timeout(d),
            "sample_time_fine_wrap": int(S.get_number(d, "sample_time_fine_wrap", 1 << 32, minimum=1000,
                                                      maximum=1 << 32, integer=True)),
            "align_wait_s": float(S.get_number(d, "align_wait_s", 0.02, minimum=0, maximum=1)),
            "link_timeout_s": float(S.get_number(d, "link_timeout_s", 2.0, minimum=0.01, maximum=600))}


def pulse_settings(driver: str, d: LocDict) -> dict[str, Any]:
    if driver in ("none", "sim"):
        return {}
    if driver == "novatel":
        S.check_keys(d, (*COMMON_KEYS, "port", "baudrate", "timeout_s", "signal", "polarity",
                         "timebias_ns", "timeguard_ms", "log"), "'pulses' (novatel)")
        return {"port": _port(d, driver), "baudrate": _baud(d, 115200), "timeout_s": _timeout(d, 1.0),
                "signal": S.get_str(d, "signal", "MARK1", choices=("MARK1", "MARK2", "MARK3", "MARK4")),
                "polarity": S.get_str(d, "polarity", "NEGATIVE", choices=("NEGATIVE", "POSITIVE")),
                "timebias_ns": int(S.get_number(d, "timebias_ns", 0, minimum=-10**9, maximum=10**9,
                                                integer=True)),
                "timeguard_ms": int(S.get_number(d, "timeguard_ms", 4, minimum=4, maximum=3_599_999,
                                                 integer=True)),
                "log": S.get_str(d, "log", "MARK1TIMEA", choices=("MARK1TIMEA", "MARKTIMEA"))}
    if driver == "gpio":
        S.check_keys(d, (*COMMON_KEYS, "chip", "line", "edge", "event_clock", "debounce_us", "bias"),
                     "'pulses' (gpio)")
        return {"chip": S.get_str(d, "chip", "/dev/gpiochip0"),
                "line": int(S.get_number(d, "line", minimum=0, maximum=65535, integer=True)),
                "edge": S.get_str(d, "edge", "rising", choices=("rising", "falling", "both")),
                "event_clock": S.get_str(d, "event_clock", "monotonic", choices=("monotonic", "realtime", "hte")),
                "debounce_us": int(S.get_number(d, "debounce_us", 0, minimum=0, maximum=10**6, integer=True)),
                "bias": S.get_str(d, "bias", "as-is", choices=("as-is", "pull-up", "pull-down", "disabled"))}
    S.check_keys(d, (*COMMON_KEYS, "port", "baudrate", "line", "edge", "mode", "poll_interval_s"),
                 "'pulses' (modem)")
    return {"port": _port(d, driver), "baudrate": _baud(d, 9600),
            "line": S.get_str(d, "line", "cd", choices=("cd", "cts", "dsr", "ri")),
            "edge": S.get_str(d, "edge", "rising", choices=("rising", "falling", "both")),
            "mode": S.get_str(d, "mode", "wait", choices=("wait", "poll")),
            "poll_interval_s": float(S.get_number(d, "poll_interval_s", 0.001, minimum=1e-4, maximum=1))}
