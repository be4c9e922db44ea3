"""The one table of display units: every quantity rigctl reports, its field unit and factor.

Inside rigctl every number is SI and every parameter name carries its SI unit
(``accel_bias_x_m_s2``, ``gyro_M_xy_ratio``). People read field units, one spelling per
quantity, the same in ``rigctl calibrate``, ``rigctl allan``, ``rigctl history``, the report,
the certificate and the results database:

=======================================  =================  ==============================
quantity                                 display unit        from SI
=======================================  =================  ==============================
accelerometer bias                       mg                  1e3 / g0 (g0 = 9.80665 m/s^2)
gyro bias                                deg/h               180/pi * 3600
scale error (diagonal of M minus 1)      ppm                 1e6 (offset 1)
misalignment (off-diagonal of M)         urad                1e6
accelerometer quadratic term             ug/g^2              g0 * 1e6
gyro g-sensitivity                       deg/h/g             180/pi * 3600 * g0
gyro N (angle random walk)               deg/sqrt(h)         180/pi * 60
accelerometer N (velocity random walk)   m/s/sqrt(h)         60
gyro B, accelerometer B                  deg/h, mg           as the biases
gyro K, accelerometer K                  deg/h/sqrt(h),      180/pi * 3600 * 60,
                                         m/s/h/sqrt(h)       3600 * 60
=======================================  =================  ==============================

(the full list is :data:`SUFFIXES` and :data:`NOISE_UNITS`). A displayed value is
``(si - offset) * factor``; an uncertainty ``u_si * |factor|``.

Digits: :func:`format_value` rounds the uncertainty to two significant digits and the value
to the same decimal place (GUM 7.2.6), so 0.0039118 +- 0.00021 reads 0.00391 +- 0.00021.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

from .solvers.noise_coefficients import FIELD_UNITS, SI_UNITS, TERM_NAMES

G0 = 9.80665  #: standard gravity, m/s^2 (1 g)
DEG = math.pi / 180.0
DEG_H = 180.0 / math.pi * 3600.0  #: (deg/h) per (rad/s)


@dataclass(frozen=True)
class Display:
    """How one parameter is shown: ``base`` name without unit, field ``unit``, and
    display = (value_si - offset) * factor."""

    base: str
    unit: str
    factor: float
    offset: float = 0.0
    si_unit: str = ""

    def value(self, v_si: float | None) -> float | None:
        """The value in the display unit (None stays None)."""
        return None if v_si is None else (float(v_si) - self.offset) * self.factor

    def sigma(self, u_si: float | None) -> float | None:
        """An uncertainty (a difference) in the display unit."""
        return None if u_si is None else float(u_si) * abs(self.factor)

    def to_si(self, v: float) -> float:
        """A value written in the display unit back to SI."""
        return v / self.factor + self.offset


#: SI name suffix -> (display unit, factor from SI, SI unit); the first match wins (longest first)
SUFFIXES: tuple[tuple[str, str, float, str], ...] = (
    ("_rad_s_per_m2_s4", "deg/h/g^2", DEG_H * G0**2, "rad/s/(m/s^2)^2"),
    ("_rad_s_per_m_s2", "deg/h/g", DEG_H * G0, "rad/s/(m/s^2)"),
    ("_m_s2_per_K_per_s", "mg/(K/min)", 1e3 / G0 / 60.0, "m/s^2/(K/s)"),
    ("_rad_s_per_K_per_s", "deg/h/(K/min)", DEG_H / 60.0, "rad/s/(K/s)"),
    ("_m_s2_per_K2", "mg/K^2", 1e3 / G0, "m/s^2/K^2"),
    ("_rad_s_per_K2", "deg/h/K^2", DEG_H, "rad/s/K^2"),
    ("_rad_per_K2", "urad/K^2", 1e6, "rad/K^2"),
    ("_rad_per_K", "urad/K", 1e6, "rad/K"),
    ("_per_K2", "ppm/K^2", 1e6, "1/K^2"),
    ("_m_s2_per_K", "mg/K", 1e3 / G0, "m/s^2/K"),
    ("_rad_s_per_K", "deg/h/K", DEG_H, "rad/s/K"),
    ("_s2_per_rad2", "ppm/(deg/s)^2", DEG**2 * 1e6, "s^2/rad^2"),
    ("_s_per_rad", "ppm/(deg/s)", DEG * 1e6, "s/rad"),
    ("_s2_per_m", "ug/g^2", G0 * 1e6, "s^2/m"),
    ("_per_K", "ppm/K", 1e6, "1/K"),
    ("_m_s3", "mg/h", 3600.0 * 1e3 / G0, "m/s^3"),
    ("_m_s2_per_h", "mg/h", 1e3 / G0, "m/s^2/h"),
    ("_rad_s_per_h", "deg/h/h", DEG_H, "rad/s/h"),
    ("_rad_s2", "deg/h/h", DEG_H * 3600.0, "rad/s^2"),
    ("_m_s2", "mg", 1e3 / G0, "m/s^2"),
    ("_rad_s", "deg/h", DEG_H, "rad/s"),
    ("_time_delay_s", "ms", 1e3, "s"),
    ("_rad", "urad", 1e6, "rad"),
    ("_m", "mm", 1e3, "m"),
    ("_ratio", "ppm", 1e6, "1"),
    ("_s", "s", 1.0, "s"),
)

#: IEEE 952 noise terms (rigctl.solvers.noise_coefficients, the one table): sensor -> term ->
#: (display unit, factor from SI); the term names per sensor (the base names of noise
#: parameters: gyro_angle_random_walk_x); the SI units (gyro rad/s-based, accelerometer m/s^2-based)
NOISE_UNITS: dict[str, dict[str, tuple[str, float]]] = FIELD_UNITS
NOISE_TERM_NAMES = TERM_NAMES
NOISE_SI = SI_UNITS

_M = re.compile(r"^(accel|gyro)_M_([xyz])([xyz])_ratio$")
_SCALE = re.compile(r"^(accel|gyro)_scale_([xyz])_(m_s2_per_m_s2|rad_s_per_rad_s|ratio)$")
_NOISE = re.compile(r"^(accel|gyro)_noise_([QNBKR])_([xyz])$")


def noise_name(sensor: str, term: str, axis: str) -> str:
    """The SI parameter name of an IEEE 952 term of one axis (``gyro_noise_N_x``; the SI
    unit is NOISE_SI[sensor][term])."""
    return f"{sensor}_noise_{term}_{axis}"


def display(name: str) -> Display:
    """How the SI parameter ``name`` is shown (base name, unit, factor, offset).

    Diagonal elements of a scale/misalignment matrix (``*_M_xx_ratio``, multipos scales) are
    shown as scale errors in ppm (offset 1); off-diagonal ratios as misalignments in urad;
    noise terms (``gyro_noise_N_x``) as ``gyro_angle_random_walk_x`` in deg/sqrt(h).
    """
    m = _M.match(name)
    if m:
        if m.group(2) == m.group(3):
            return Display(f"{m.group(1)}_scale_error_{m.group(2)}", "ppm", 1e6, 1.0, "1")
        return Display(f"{m.group(1)}_misalignment_{m.group(2)}{m.group(3)}", "urad", 1e6, 0.0, "rad")
    m = _SCALE.match(name)
    if m:
        return Display(f"{m.group(1)}_scale_error_{m.group(2)}", "ppm", 1e6, 1.0, "1")
    m = _NOISE.match(name)
    if m:
        sensor, term, axis = m.groups()
        unit, fac = NOISE_UNITS[sensor][term]
        return Display(f"{sensor}_{NOISE_TERM_NAMES[sensor][term]}_{axis}", unit, fac, 0.0,
                       NOISE_SI[sensor][term])
    for suf, unit, fac, si in SUFFIXES:
        if name.endswith(suf):
            return Display(name[: -len(suf)], unit, fac, 0.0, si)
    return Display(name, "1", 1.0, 0.0, "1")


def slug(unit: str) -> str:
    """A display unit as a key suffix: 'deg/sqrt(h)' -> 'deg_per_sqrt_h', 'deg/h' -> 'deg_per_h'."""
    return re.sub(r"[()]", "", unit.replace("/", "_per_").replace("(", "_")).replace("^", "")


#: how many significant digits of the uncertainty are shown
U_DIGITS = 2


def decimals_for(u: float, digits: int = U_DIGITS) -> int | None:
    """Decimal places that show ``u`` with ``digits`` significant digits (negative: round to
    tens, hundreds...); None when u is not a positive finite number."""
    if u is None or not math.isfinite(u) or u <= 0:
        return None
    return digits - 1 - math.floor(math.log10(u))


def _fixed(x: float, dec: int) -> str:
    if dec >= 0:
        return f"{x:.{dec}f}"
    q = 10.0 ** (-dec)
    return f"{round(x / q) * q:.0f}"


def format_value(v: float | None, u: float | None = None, digits: int = U_DIGITS) -> tuple[str, str]:
    """(value text, uncertainty text) with the uncertainty to ``digits`` significant digits and
    the value rounded to the same decimal place; without a usable uncertainty the value gets
    five significant digits and the uncertainty 'n/a'."""
    if v is None or not math.isfinite(v):
        return "n/a", format_value(u)[0] if u is not None and math.isfinite(u) else "n/a"
    dec = decimals_for(u, digits) if u is not None else None
    if dec is None:
        return f"{v:.5g}", "n/a"
    # rounding u can carry into another digit (0.0996 -> 0.10): recompute from the rounded u
    ur = round(u, dec) if dec >= 0 else round(u / 10.0 ** (-dec)) * 10.0 ** (-dec)
    dec = decimals_for(ur, digits) or dec
    if dec > 9:  # tiny numbers: scientific notation with the same rule
        n = digits - 1 + (max(0, math.floor(math.log10(abs(v))) - math.floor(math.log10(ur))) if v else 0)
        return f"{v:.{n}e}", f"{ur:.{digits - 1}e}"
    return _fixed(v, dec), _fixed(u, dec)


def format_number(v: float | None, u: float | None) -> str:
    """A number alone rounded like :func:`format_value` (e.g. an interval end)."""
    return format_value(v, u)[0]


def capture_text(h: float) -> str:
    """A capture length in hours for people: '40 min', '2.5 h', '47 h', '12 days'; inf (beyond
    what allan_crb.duration_for considers) 'more than 417 days'."""
    if not math.isfinite(h):
        from .solvers.allan_crb import MAX_CAPTURE_S

        return f"more than {MAX_CAPTURE_S / 86400:.0f} days"
    if h < 1.0:
        return f"{max(1.0, h * 60.0):.0f} min"
    if h < 10.0:
        return f"{h:.1f} h"
    return f"{h:.0f} h" if h < 72 else f"{h / 24:.0f} days"


def need_text(e: dict, resolved: bool) -> str:
    """How long a capture would resolve an Allan term to +-25 % (95 %), honestly: for a resolved
    term about the Cramer-Rao length; for a bounded term at least the length at which a term as
    large as its bound would be resolved -- and where that is no longer than this capture, only
    that a longer capture is needed (how much longer depends on the term's unknown size)."""
    need = e.get("capture_h_for_25pct")
    if need is None:
        return ""
    if resolved:
        return f"+-25 % needs about {capture_text(need)}"
    have = e.get("capture_h")
    if have is not None and need <= 1.05 * have:
        return (f"+-25 % needs a longer capture than this one ({capture_text(have)}); how much "
                "longer depends on the term's size, which this capture only bounds")
    return f"+-25 % would need at least {capture_text(need)} of capture"
