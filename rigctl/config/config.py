"""Rig configuration: which devices, the table's limits, the site, the clock, the recorder."""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from .. import schema as S
from .chamber import ChamberSettings, chamber_settings
from ..frames import normal_gravity
from .linkconfig import COMMON_KEYS, LinkSettings, link_settings
from .notify import NotifySettings, notify_settings
from ..settings import Settings, number, parse, section, setting, text
from .suspenders import SuspenderSettings
from ..errors import InputError
from ..yamlio import LocDict, load_file

#: Where the project's shipped files live (beside the package in a checkout / editable install).
PROJECT_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_CONFIG = "configs/sim.yaml"

TABLE_DRIVERS = ("sim", "acl", "modbus")
IMU_DRIVERS = ("sim", "xsens", "vectornav", "frame")
PULSE_DRIVERS = ("none", "sim", "novatel", "gpio", "modem", "vectornav")
CHAMBER_DRIVERS = ("none", "sim", "watlow", "scpi")
CLOCKS = ("virtual", "real", "scaled")


@dataclass(frozen=True)
class TableLimits:
    """Demand limits per axis [outer, middle, inner]: rate rad/s, acceleration rad/s^2,
    angle range rad ((-inf, inf) for a continuous axis)."""

    rate: np.ndarray
    accel: np.ndarray
    angle_min: np.ndarray
    angle_max: np.ndarray

    def check(self, angles: np.ndarray | None = None, rates: np.ndarray | None = None) -> None:
        """Raise ValueError naming the axis and the limit when a demand is out of range."""
        names = ("outer", "middle", "inner")
        if angles is not None:
            for i, a in enumerate(angles):
                if not (self.angle_min[i] <= a <= self.angle_max[i]):
                    raise ValueError(
                        f"{names[i]} angle {math.degrees(a):.3f} deg is outside the table's range "
                        f"[{math.degrees(self.angle_min[i]):.1f}, {math.degrees(self.angle_max[i]):.1f}] deg")
        if rates is not None:
            for i, r in enumerate(rates):
                if not math.isnan(r) and abs(r) > self.rate[i] * (1 + 1e-12):
                    raise ValueError(
                        f"{names[i]} rate {math.degrees(r):.3f} deg/s exceeds the table's limit "
                        f"{math.degrees(self.rate[i]):.1f} deg/s")


@dataclass(frozen=True, kw_only=True)
class SiteSettings(Settings):
    """``site:``: where the rig stands (normal gravity from latitude and height, unless the
    locally measured gravity is given)."""

    latitude_deg: float = number(45.0, minimum=-90, maximum=90)
    height_m: float = number(0.0, minimum=-500, maximum=10000)
    gravity_m_s2: float | None = number(None, minimum=9.7, maximum=9.9, allow_none=True)


@dataclass(frozen=True, kw_only=True)
class RecorderSettings(Settings):
    """``recorder:``: how often the recording is flushed to disk, and the table's sample rate."""

    flush_interval_s: float = number(0.5, minimum=0.01, maximum=1.0)
    table_rate_hz: float = number(10.0, minimum=0.1, maximum=1000.0)


@dataclass(frozen=True, kw_only=True)
class RigSettings(Settings):
    """The rig config's top level (each section is read by its own settings)."""

    EXTRA_KEYS: ClassVar[tuple[str, ...]] = ("site", "table", "imu", "pulses", "recorder", "suspenders",
                                             "traceability", "chamber", "notifications")
    rig: str | None = text(None)
    #: None: virtual with the emulator, real with wired devices
    clock: str | None = text(None, choices=CLOCKS)
    speed: float = number(1.0, minimum=1e-3, maximum=1e4)
    seed: int = number(0, minimum=0, integer=True)


@dataclass(frozen=True)
class DeviceConfig:
    """A device section: its driver, the raw options, and the validated settings: for the
    table, IMU and pulse input a :class:`rigctl.config.linkconfig.LinkSettings` of a wired driver (None
    for the in-process emulator); for the chamber a :class:`rigctl.config.chamber.ChamberSettings`."""

    driver: str
    options: LocDict
    settings: LinkSettings | ChamberSettings | None = None


@dataclass(frozen=True)
class RigConfig:
    """A validated rig configuration. Angles in rad, rates in rad/s, times in s."""

    path: str
    text: str
    name: str
    clock: str
    speed: float
    latitude: float
    height_m: float
    gravity_measured: float | None
    limits: TableLimits
    table: DeviceConfig
    imu: DeviceConfig
    imu_rate_hz: float
    pulses: DeviceConfig
    flush_interval_s: float = 0.5
    table_rate_hz: float = 10.0
    seed: int = 0
    #: the unit under test as declared by ``imu.serial`` ("" when not given)
    imu_serial: str = ""
    suspenders: SuspenderSettings = field(default_factory=SuspenderSettings)
    raw: LocDict = field(default_factory=LocDict, repr=False)
    #: the climatic chamber (docs/thermal.md): ``none``, ``sim`` (in the emulated world),
    #: ``watlow`` (Modbus RTU / TCP) or ``scpi`` (PyVISA); settings from rigctl.config.chamber
    chamber: DeviceConfig = field(default_factory=lambda: DeviceConfig("none", LocDict(), ChamberSettings()))
    #: the daemon's notices (docs/daemon.md): webhook and/or e-mail on job end, suspension, fault
    notifications: NotifySettings = field(default_factory=NotifySettings)

    @property
    def gravity(self) -> float:
        """Local gravity, m/s^2: the measured value if configured, else WGS-84 normal gravity."""
        if self.gravity_measured is not None:
            return self.gravity_measured
        return normal_gravity(self.latitude, self.height_m)

    @property
    def is_simulated(self) -> bool:
        return self.table.driver == "sim" and self.imu.driver == "sim"


def _three(m: LocDict, key: str, default: Any = None) -> tuple[float, ...]:
    """Three positive numbers [outer, middle, inner]."""
    v = S.number_list(m, key, length=3)
    if any(x <= 0 for x in v):
        raise S.error(m, key, f"{key!r} entries must be positive")
    return tuple(v)


def _angle_ranges(m: LocDict, key: str, default: Any = None) -> tuple[tuple[float, float] | None, ...]:
    """Per axis null (continuous) or [min, max] in degrees."""
    v = S.get_list(m, key, length=3)
    for i, r in enumerate(v):
        if r is not None and not (isinstance(r, list) and len(r) == 2 and all(
                isinstance(x, (int, float)) for x in r) and r[0] < r[1]):
            raise S.error(m, key, f"angle_deg entry {i + 1} must be null (continuous) or "
                          "[min, max] in degrees with min < max")
    return tuple(None if r is None else (r[0], r[1]) for r in v)


@dataclass(frozen=True, kw_only=True)
class TableLimitSettings(Settings):
    """``table.limits``: the demands a procedure may make, [outer, middle, inner] (the table's
    own limits, or tighter)."""

    rate_dps: tuple[float, ...] = setting((300.0, 300.0, 500.0), read=_three)
    accel_dps2: tuple[float, ...] = setting((200.0, 200.0, 400.0), read=_three)
    angle_deg: tuple[tuple[float, float] | None, ...] = setting((None, None, None), read=_angle_ranges)

    def limits(self) -> TableLimits:
        """In SI (rad, rad/s, rad/s^2)."""
        lo = np.array([-np.inf if r is None else math.radians(r[0]) for r in self.angle_deg])
        hi = np.array([np.inf if r is None else math.radians(r[1]) for r in self.angle_deg])
        return TableLimits(rate=np.radians(np.asarray(self.rate_dps, dtype=float)),
                           accel=np.radians(np.asarray(self.accel_dps2, dtype=float)),
                           angle_min=lo, angle_max=hi)


def _device(m: LocDict, key: str, drivers: tuple[str, ...], default_driver: str | None,
            extra: tuple[str, ...] = ()) -> tuple[DeviceConfig, LocDict]:
    if key not in m:
        if default_driver is None:
            raise S.error(m, None, f"the config has no {key!r} section", f"add '{key}:' with a driver")
        d = LocDict(driver=default_driver)
        return DeviceConfig(default_driver, d), d
    d = S.require_mapping(m[key], f"the {key!r} section", m, key)
    driver = S.get_str(d, "driver", choices=drivers)
    return DeviceConfig(driver, d), d


#: longest ``imu.serial`` accepted, characters
SERIAL_MAX_CHARS = 64


def imu_serial(d: LocDict) -> str:
    """``imu.serial``: the unit under test as the lab names it (its label, for an IMU that
    cannot report its own ID), kept as /meta ``imu_serial``. Text of at most SERIAL_MAX_CHARS
    printable characters; absent, null or "" = not declared (""). A YAML number is refused,
    not converted: ``serial: 0123`` would read as 83 (octal) and lose the label."""
    if d.get("serial") is None:
        return ""
    v = d["serial"]
    if not isinstance(v, str):
        raise S.error(d, "serial", f"'serial' must be text, got {v!r}",
                      f'quote it so it is kept exactly as written: serial: "{v}"')
    v = v.strip()
    if len(v) > SERIAL_MAX_CHARS or not v.isprintable():
        raise S.error(d, "serial", f"'serial' must be at most {SERIAL_MAX_CHARS} printable characters "
                      "on one line", "give the unit's serial number or label")
    return v


def suspender_settings(m: LocDict) -> SuspenderSettings:
    """The ``suspenders:`` section of a rig config (absent keys keep their defaults): the
    fields of :class:`rigctl.config.suspenders.SuspenderSettings`."""
    return section(m, "suspenders", SuspenderSettings)


def _statement(d: LocDict, key: str, default: str) -> str:
    """Text of at most 500 characters; a list of texts (``reference_standards``) joined by '; '."""
    v = d[key]
    if isinstance(v, list) and all(isinstance(x, str) for x in v):
        v = "; ".join(v)
    if not isinstance(v, str) or not v.strip() or len(v) > 500:
        raise S.error(d, key, f"'{key}' must be text (at most 500 characters)", f'quote it: {key}: "..."')
    return v.strip()


def _stated(default: str = "") -> Any:
    return setting(default, read=_statement)


@dataclass(frozen=True, kw_only=True)
class Traceability(Settings):
    """``traceability:``: what a certificate states about the laboratory and the traceability of
    the rig (docs/production.md); "" = not stated."""

    laboratory: str = _stated()
    address: str = _stated()
    accreditation: str = _stated()
    table_id: str = _stated()
    table_calibration: str = _stated()
    table_calibration_due: str = _stated()
    reference_standards: str = _stated()
    procedure_document: str = _stated()


def traceability(m: LocDict) -> dict[str, str]:
    """The ``traceability:`` section of a rig config as {field: text}, the fields stated only
    (absent section: {})."""
    t = section(m, "traceability", Traceability)
    return {f.name: getattr(t, f.name) for f in fields(t) if getattr(t, f.name)}


def load_config(path: str | Path) -> RigConfig:
    """Load and validate a rig config file; InputError names the file and line of any problem."""
    p = Path(path)
    raw = load_file(p)
    if raw is None:
        raise InputError("the config file is empty", p)
    m = S.require_mapping(raw, "a rig config")
    top = parse(RigSettings, m, "the rig config")
    traceability(m)
    name, clock, speed, seed = top.rig if top.rig is not None else p.stem, top.clock, top.speed, top.seed

    site = section(m, "site", SiteSettings)
    lat, h, g = math.radians(site.latitude_deg), site.height_m, site.gravity_m_s2

    table, t = _device(m, "table", TABLE_DRIVERS, None)
    if table.driver == "sim":
        S.check_keys(t, ("driver", "limits", "sim"), "'table'")
    table = DeviceConfig(table.driver, t, link_settings("table", table.driver, t))
    limits = section(t, "limits", TableLimitSettings, "'table.limits'").limits()

    imu, i = _device(m, "imu", IMU_DRIVERS, None)
    if imu.driver == "sim":
        S.check_keys(i, (*COMMON_KEYS, "serial"), "'imu' (sim)")
    imu_rate = S.get_number(i, "rate_hz", 100.0, minimum=1.0, maximum=10000.0)
    serial = imu_serial(i)
    imu = DeviceConfig(imu.driver, i, link_settings("imu", imu.driver, i))
    pulses, p_opts = _device(m, "pulses", PULSE_DRIVERS, "none")
    pulses = DeviceConfig(pulses.driver, p_opts, link_settings("pulses", pulses.driver, p_opts))
    if pulses.driver == "vectornav":
        S.check_keys(p_opts, ("driver",), "'pulses' (vectornav)")
        if imu.driver != "vectornav":
            raise S.error(m, "pulses", f"pulses from a VectorNav's SYNC_IN need the VectorNav as the IMU "
                          f"(the imu driver is '{imu.driver}')",
                          "set imu: driver: vectornav, or choose another pulse source (novatel, gpio, modem)")
    if (table.driver == "sim") != (imu.driver == "sim"):
        raise S.error(m, "table", "the in-process emulator ('sim') drives the table and the IMU "
                      "together; mixing it with a wired device is not supported",
                      "use driver: sim for both, or wired drivers for both (configs/sim-wire.yaml)")
    if clock is None:
        clock = "virtual" if table.driver == "sim" else "real"
    elif clock == "virtual" and table.driver != "sim":
        raise S.error(m, "clock", "virtual time cannot drive wired devices",
                      "use clock: real (hardware) or clock: scaled with the emulator's speed "
                      "(rigctl sim up --speed X)")

    rec = section(m, "recorder", RecorderSettings)
    flush, table_rate = rec.flush_interval_s, rec.table_rate_hz
    suspenders = suspender_settings(m)
    notifications = notify_settings(m)
    chamber, c_opts = _device(m, "chamber", CHAMBER_DRIVERS, "none")
    chamber = DeviceConfig(chamber.driver, c_opts, chamber_settings(chamber.driver, c_opts))
    # driver: sim is the in-process world's chamber; a wired rig has no in-process world, so
    # there it means no chamber (the wired emulator's chambers: driver watlow / scpi)

    return RigConfig(path=str(p), text=p.read_text(encoding="utf-8"), name=name, clock=clock,
                     speed=speed, latitude=lat, height_m=h, gravity_measured=g, limits=limits,
                     table=table, imu=imu, imu_rate_hz=imu_rate, pulses=pulses,
                     flush_interval_s=flush, table_rate_hz=table_rate, seed=seed, imu_serial=serial,
                     suspenders=suspenders, raw=m, chamber=chamber, notifications=notifications)


def resolve_config_path(path: str | Path | None) -> Path:
    """The config to use: the given path, else configs/sim.yaml (current dir, then the project)."""
    if path is not None:
        return Path(path)
    for base in (Path.cwd(), PROJECT_ROOT):
        candidate = base / DEFAULT_CONFIG
        if candidate.is_file():
            return candidate
    raise InputError(f"no --config given and {DEFAULT_CONFIG} was not found",
                     hint="run from the rigctl checkout or pass --config FILE")


def describe_options(options: LocDict) -> dict[str, Any]:
    """Plain dict copy of a device's options (for provenance)."""
    return {k: v for k, v in options.items()}
