"""Allan results in the formats their consumers read: Kalibr's imu.yaml, JSON, a CSV table.

Pure functions of the result that ``rigctl allan`` computes (per axis: the deviation curve with
its bands and the fitted IEEE 952 coefficients, ``fit["coefficients"]``: a
:class:`~rigctl.solvers.noise_coefficients.NoiseCoefficients`, or its stored JSON form, whose
terms carry SI values and 95 % intervals, or a 95 % upper bound for a term the data do not
support; docs/allan.md).

Kalibr (and OpenVINS, which reads the same keys from ``kalibr_imu_chain.yaml``) models each
sensor as white noise plus a random-walk bias, in continuous time:

=============================  ================  ==========================================
key                            unit              IEEE 952 term (SI unit, same number)
=============================  ================  ==========================================
``gyroscope_noise_density``    rad/s/sqrt(Hz)    gyro N, angle random walk (rad/sqrt(s))
``gyroscope_random_walk``      rad/s^2/sqrt(Hz)  gyro K, rate random walk (rad/s/sqrt(s))
``accelerometer_noise_density``  m/s^2/sqrt(Hz)  accel N, velocity random walk (m/s/sqrt(s))
``accelerometer_random_walk``  m/s^3/sqrt(Hz)    accel K, acceleration random walk
                                                 (m/s^2/sqrt(s))
=============================  ================  ==========================================

since 1/sqrt(s) = sqrt(Hz): rad/sqrt(s) = rad/s/sqrt(Hz) and rad/s/sqrt(s) = rad/s^2/sqrt(Hz).
The model has one value per sensor; rigctl writes the **largest of the three axes** (for a term
bounded on an axis, its 95 % upper bound counts): an estimator given the largest noise is not
over-confident on any axis. Each value's 95 % interval is that axis' interval ([0, bound] for a
bound). Bias instability B has no place in this model and is not written (it is in the comment
block). ``inflate`` multiplies all four values (users of visual-inertial estimators often
inflate by 2-10 for unmodelled effects); the file states the factor and the fitted values.
"""
from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..jsonable import jsonable
from ..solvers.noise_coefficients import Coefficient, as_coefficients

#: (sensor, term) -> (Kalibr key, unit of the key)
KALIBR_KEYS = {("accel", "N"): ("accelerometer_noise_density", "m/s^2/sqrt(Hz)"),
               ("accel", "K"): ("accelerometer_random_walk", "m/s^3/sqrt(Hz)"),
               ("gyro", "N"): ("gyroscope_noise_density", "rad/s/sqrt(Hz)"),
               ("gyro", "K"): ("gyroscope_random_walk", "rad/s^2/sqrt(Hz)")}
#: Kalibr's default topic when the recording does not name one
DEFAULT_TOPIC = "/imu0"


@dataclass
class KalibrValue:
    """One Kalibr key: the combined (largest-axis) value, the value written (``value *
    inflate``), and every axis' fitted coefficient (SI). For an axis whose term is known only
    as a 95 % upper bound, the bound counts (:attr:`Coefficient.cautious`)."""

    key: str
    unit: str
    sensor: str
    term: str
    axis: str  # the axis that gives the value
    fitted: Coefficient  # that axis' coefficient
    written: float
    axes: dict[str, Coefficient]

    @property
    def value(self) -> float:
        """The combined value before inflation: the largest axis' estimate or bound."""
        return self.fitted.cautious


def axis_coefficient(r: Mapping[str, Any], term: str) -> Coefficient:
    """The fitted ``term`` (N, B, K, ...) of one axis' result ``r`` (SI)."""
    return getattr(as_coefficients(r["fit"]["coefficients"]), term)


def kalibr_values(result: Mapping[str, Any], inflate: float = 1.0) -> list[KalibrValue]:
    """The four Kalibr values from an Allan result with all six axes (ValueError otherwise)."""
    if not inflate > 0 or not math.isfinite(inflate):
        raise ValueError(f"the inflation factor must be a positive number, not {inflate!r}")
    out = []
    for (sensor, term), (key, unit) in KALIBR_KEYS.items():
        axes = {a: axis_coefficient(r, term) for a, r in result["axes"].items() if r["sensor"] == sensor}
        if len(axes) != 3:
            raise ValueError(f"{key} needs the three {sensor} axes, the result has {len(axes)}")
        top = max(axes, key=lambda a: axes[a].cautious)
        out.append(KalibrValue(key, unit, sensor, term, top, axes[top], axes[top].cautious * inflate, axes))
    return out


def _e(x: float) -> str:
    """A float YAML 1.1 (PyYAML) reads as a float: mantissa with a point, signed exponent."""
    return f"{x:.6e}"


def _bound(c: Coefficient) -> str:
    return "" if c.resolved else " (bound)"


def kalibr_yaml(result: Mapping[str, Any], rostopic: str, inflate: float = 1.0) -> str:
    """Kalibr's imu.yaml text: a comment block (source, capture, how the values were made,
    each value's 95 % interval and the inflation), then the six keys."""
    vals = kalibr_values(result, inflate)
    n, fs = int(result["n_samples"]), float(result["sample_rate_hz"])
    lines = [
        "# IMU noise parameters for Kalibr (imu.yaml; OpenVINS reads the same keys in kalibr_imu_chain.yaml)",
        f"# written by rigctl allan from {result.get('file', '?')}, {result.get('segment', 'whole recording')}:",
        f"# {n} samples at {fs:.8g} Hz ({n / fs / 3600:.3g} h), {int(result.get('dropped_samples', 0))} "
        "samples missing (counter gaps)",
        "# noise density = IEEE 952 N (white noise), random walk = IEEE 952 K (bias random walk), SI,",
        "# continuous time; per sensor the LARGEST of the three axes (an axis' 95 % upper bound where",
        "# the data resolve no term there). Intervals: 95 %, of the axis that gives the value.",
    ]
    if inflate == 1.0:
        lines.append("# inflation: none (the fitted values are written as they are)")
    else:
        lines.append(f"# inflation: x{inflate:g} chosen by the user (--kalibr-inflate): every value below "
                     "is the fitted value times this factor")
    for v in vals:
        lo, hi = v.fitted.interval95
        kind = "fitted" if v.fitted.resolved else "95 % upper bound (not resolved by this capture)"
        lines.append(f"# {v.key} [{v.unit}]: {kind} {_e(v.value)} on {v.axis}, 95 % interval "
                     f"[{_e(lo)}, {_e(hi)}]" + ("" if inflate == 1.0 else
                                                f"; written x{inflate:g} = {_e(v.written)}"))
        per = ", ".join(f"{a} {_e(c.cautious)}{_bound(c)}" for a, c in v.axes.items())
        lines.append(f"#   per axis: {per}")
    lines.append("# bias instability B (not in Kalibr's model), per axis, SI (rad/s, m/s^2): " + ", ".join(
        f"{a} {_e(b.cautious)}{_bound(b)}" for a, b in
        ((a, axis_coefficient(r, "B")) for a, r in result["axes"].items())))
    lines += gm_comment(result)
    lines.append("")
    for sensor, title in (("accel", "Accelerometers"), ("gyro", "Gyroscopes")):
        lines.append(f"#{title}")
        for v in vals:
            if v.sensor == sensor:
                lines.append(f"{v.key}: {_e(v.written)}   # [{v.unit}]")
        lines.append("")
    lines.append(f"rostopic: {json.dumps(rostopic)}")
    lines.append(f"update_rate: {fs:.6f}   # Hz")
    return "\n".join(lines) + "\n"


def gm_comment(result: Mapping[str, Any]) -> list[str]:
    """Comment lines for the axes whose joint fit holds a first-order Gauss-Markov term
    (``coefficients.gm``): Kalibr's model has none, so it is not exported; the N and K above
    are those fitted with it in the model. [] when no axis has one."""
    rows = []
    for a, r in result["axes"].items():
        co = as_coefficients(r["fit"]["coefficients"])
        for g in co.gm:
            lo, hi = g.sigma.interval95
            tc = "" if g.tau_c_ci95 is None else f" {g.tc_interval_text(4)}"
            kind = "" if g.sigma.resolved else " (bound)"
            rows.append(f"#   {a}: sigma_GM {_e(g.sigma.cautious)}{kind} [{_e(lo)}, {_e(hi)}] "
                        f"(rad/s or m/s^2), Tc {g.tau_c_s:.4g} s{tc} (95 %)")
    if not rows:
        return []
    return ["# a first-order Gauss-Markov term was fitted (beside the IEEE 952 terms; the noise",
            "# densities and random walks above were fitted with it in the model) and is NOT",
            "# exported: Kalibr's model (white noise + random-walk bias) has no such term.",
            *rows,
            "# To carry it in a white + random-walk model (docs/allan.md, 'Where the values go'):",
            "# over times well below Tc it acts as a random walk, K^2 = 2 sigma_GM^2 / Tc; well above",
            "# Tc as white noise, N^2 = 2 sigma_GM^2 Tc; add the one that matches the estimator's",
            "# horizon to the written value's square (or model it as an extra bias state)."]


def imu_topic(meta: Mapping[str, Any]) -> str:
    """The IMU topic a recording came from (``/meta`` ``import_topic`` of a bag import), else
    Kalibr's default ``/imu0``."""
    t = meta.get("import_topic", "")
    t = t.decode() if isinstance(t, bytes) else str(t)
    return t or DEFAULT_TOPIC


def allan_json(result: Mapping[str, Any], kalibr: list[KalibrValue] | None = None) -> str:
    """The whole Allan result as JSON (units in the key names, as stored in /results/allan;
    non-finite numbers as null), plus the Kalibr values when given."""
    doc = jsonable(result)
    if kalibr is not None:
        doc["kalibr"] = {v.key: {"unit": v.unit, "written": v.written, "fitted": v.value,
                                 "axis": v.axis, "supported": v.fitted.resolved,
                                 "ci95": list(v.fitted.interval95)} for v in kalibr}
    return json.dumps(doc, indent=1, allow_nan=False) + "\n"


CSV_COLUMNS = ("axis", "sensor", "unit", "tau_s", "m", "n_terms", "sigma", "lo68", "hi68", "lo95",
               "hi95", "edf", "alpha")


def deviation_csv(result: Mapping[str, Any]) -> str:
    """The deviation table, one row per axis and tau, in SI (``unit``: rad/s or m/s^2): sigma
    (overlapping Allan deviation), its 68 % and 95 % bands, the number of terms averaged, the
    equivalent degrees of freedom and the noise type alpha used for them."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for axis, r in result["axes"].items():
        si, unit = r["_si"], r["_unit"]
        sig = np.asarray(r[f"adev_{si}"], float)
        shown = np.asarray(r[f"adev_{unit}"], float)
        scale = np.divide(sig, shown, out=np.zeros_like(sig), where=shown != 0)  # SI per display unit
        band = {k: np.asarray(r[f"{k}_{unit}"], float) * scale for k in ("lo68", "hi68", "lo95", "hi95")}
        for i, tau in enumerate(np.asarray(r["tau_s"], float)):
            w.writerow([axis, r["sensor"], si, repr(float(tau)), int(r["m"][i]), int(r["n_terms"][i]),
                        repr(float(sig[i])), *(repr(float(band[k][i])) for k in ("lo68", "hi68", "lo95", "hi95")),
                        repr(float(r["edf"][i])), int(r["alpha"][i])])
    return buf.getvalue()


def write_exports(recording: str, result: dict, kalibr_path: str | None, inflate: float,
                  topic: str | None, json_path: str | None, csv_path: str | None) -> list[str]:
    """Write the exports ``rigctl allan`` was asked for (Kalibr imu.yaml, the whole result as
    JSON, the deviation table as CSV); returns one line per file written."""
    from pathlib import Path

    out = []
    kalibr = kalibr_values(result, inflate) if kalibr_path else None
    if kalibr_path:
        import h5py

        with h5py.File(recording, "r") as f:
            topic = topic or imu_topic(f["meta"].attrs if "meta" in f else {})
        Path(kalibr_path).write_text(kalibr_yaml(result, topic, inflate))
        out.append(f"Kalibr imu.yaml written to {kalibr_path}"
                   + ("" if inflate == 1 else f" (values x{inflate:g})"))
    if json_path:
        Path(json_path).write_text(allan_json(result, kalibr))
        out.append(f"JSON written to {json_path}")
    if csv_path:
        Path(csv_path).write_text(deviation_csv(result))
        out.append(f"deviation table written to {csv_path}")
    return out
