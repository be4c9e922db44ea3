"""The one spelling of the IMU's six sensor axes, for every command and the report.

``ax ay az`` are the accelerometer's x, y, z (``/imu/specific_force`` columns 0, 1, 2) and
``gx gy gz`` the gyro's (``/imu/angular_rate`` columns 0, 1, 2), in the body frame. This is
the spelling the recording format already fixed: ``/results/allan`` holds one group per axis
under these names (``/results/allan/gx/tau_s``, docs/data-format.md), ``rigctl allan --axes``
takes them, and ``/meta import_axes`` lists them. Every command prints and writes only these
(text, JSON keys and values, CSV, the HTML report, the Kalibr comment block).

Older spellings that were documented *inputs* -- ``acc_x``/``gyr_x`` (``rigctl import
--columns``), ``accel_x``/``gyro_x`` (a declarative frame's field names; the channel names
``rigctl calibrate`` printed) -- are accepted everywhere an axis is read (:func:`canonical`),
so old command lines, column maps and rig configs keep working.
"""
from __future__ import annotations

#: accelerometer x, y, z, then gyro x, y, z: the solvers' channel order
ACCEL_AXES: tuple[str, str, str] = ("ax", "ay", "az")
GYRO_AXES: tuple[str, str, str] = ("gx", "gy", "gz")
AXES: tuple[str, ...] = ACCEL_AXES + GYRO_AXES
#: the sensor each axis belongs to (the names of rigctl.display_units.NOISE_UNITS' keys)
SENSOR: dict[str, str] = {**{a: "accel" for a in ACCEL_AXES}, **{g: "gyro" for g in GYRO_AXES}}

#: old spellings still read as input: {alias: canonical}
ALIASES: dict[str, str] = {f"{prefix}_{c}": f"{a[0]}{c}"
                           for a, prefixes in (("ax", ("acc", "accel")), ("gx", ("gyr", "gyro")))
                           for prefix in prefixes for c in "xyz"}


def axis_name(sensor: str, index: int) -> str:
    """The axis ``index`` (0, 1, 2 = x, y, z) of ``sensor`` ('accel' or 'gyro'): 'ax' ... 'gz'."""
    return (ACCEL_AXES if sensor == "accel" else GYRO_AXES)[index]


def canonical(name: str) -> str | None:
    """The canonical spelling of an axis name given as input (itself, or an old alias such as
    'gyr_x', 'gyro_x', 'acc_x', 'accel_x'; case and surrounding blanks ignored); None when it
    names no axis."""
    key = name.strip().lower()
    return key if key in SENSOR else ALIASES.get(key)
