"""Foreign IMU logs (CSV, ROS 1 / ROS 2 bags, MCAP) as rigctl recordings: the application
layer of ``rigctl import`` (docs/calibration.md, docs/ros.md).

Data from other tools (hand-held multi-position sessions, loggers, other calibration tools)
enter the same pipeline as rig recordings: ``rigctl calibrate``, ``rigctl allan`` and
``rigctl apply-cal`` read the file :func:`import_file` writes (docs/data-format.md, status
``complete``). The options (:class:`ImportOptions`) are those of the command; bags are read by
:mod:`rigctl.analysis.bag_import`. InputError (exit 2) for anything in the input or options that
cannot be used, naming the file, the line and what to do.
"""
from __future__ import annotations

import csv
import gzip
import json
import zlib
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .. import __version__
from ..devices import ImuBlock
from ..errors import InputError
from ..frames import normal_gravity
from ..recording.recording_reader import MAX_RATE_HZ, PLAUSIBLE
from ..sensor_axes import ACCEL_AXES, AXES, GYRO_AXES, SENSOR, axis_name, canonical
from ..units import format_rate
from . import bag_import as B

#: progress(done, total) while a bag is read (messages)
Progress = Callable[[int, int], None]


@dataclass
class ImportOptions:
    """The options of ``rigctl import`` (the CLI's names with - as _; docs/calibration.md)."""

    file: str | Path
    output: str | Path
    columns: str | None = None      # CSV: ax=COL,...,gz=COL or a YAML/JSON mapping file
    units: str | None = None        # CSV: acc=g,gyr=deg/s, counts:SCALE UNIT, time=s|ms|us
    rate: float | None = None       # CSV: nominal sample rate, Hz
    skip_rows: int = 0              # CSV: lines before the header
    topic: str | None = None        # bag/MCAP: the sensor_msgs/Imu topic
    time_source: str = "header"     # bag/MCAP: header | receive
    segments: str | None = None     # sections JSON
    t_init: float = 5.0             # s of initial rest for automatic static detection
    gravity: float | None = None    # m/s^2
    latitude_deg: float | None = None
    force: bool = False             # replace an existing output
    integrated: bool = False        # CSV: angle/velocity columns are running integrals


G0 = 9.80665
DEG = math.pi / 180.0
#: the sensor columns, by their one spelling (rigctl.sensor_axes; acc_x, gyr_x, accel_x, gyro_x
#: ... are read as these)
REQUIRED = AXES
OPTIONAL = ("time", "temp", "section")
UNIT_FACTORS = {
    "acc": {"g": G0, "mg": G0 * 1e-3, "m/s^2": 1.0, "m/s2": 1.0},
    "gyr": {"deg/s": DEG, "rad/s": 1.0, "deg/h": DEG / 3600.0, "mrad/s": 1e-3},
    # d: days, e.g. the MJD time tags of a Stable32 two-column file (53000.000011574)
    "time": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9, "min": 60.0, "h": 3600.0, "d": 86400.0},
}
#: units of per-sample increments (delta angle, delta velocity): divided by the sample interval;
#: with --integrated the column is their running sum (an angle, a velocity, a clock's phase)
INCREMENT_UNITS = {"gyr": {"rad": 1.0, "deg": DEG, "mrad": 1e-3, "urad": 1e-6},
                   "acc": {"m/s": 1.0, "mm/s": 1e-3}}
NAN3 = np.full(3, np.nan)


def parse_columns(text: str) -> dict[str, str]:
    """Column map from ``k=v,...`` or from a YAML/JSON mapping file."""
    p = Path(text)
    if "=" not in text and p.suffix.lower() in (".yaml", ".yml", ".json"):
        if not p.is_file():
            raise InputError("column map file not found", p, hint="give key=value pairs or a YAML/JSON file")
        try:
            data = yaml.safe_load(p.read_text(encoding="utf-8"))
        except yaml.YAMLError as exc:
            line = getattr(getattr(exc, "problem_mark", None), "line", None)
            raise InputError(f"not valid YAML/JSON ({exc})", p, None if line is None else line + 1) from None
        if not isinstance(data, dict):
            raise InputError("the column map must be a mapping like ax: AccX", p, 1)
        mapping = {str(k): str(v) for k, v in data.items()}
        src: Any = p
    else:
        mapping = {}
        for part in filter(None, (s.strip() for s in text.split(","))):
            if "=" not in part:
                raise InputError(f"--columns: {part!r} is not KEY=COLUMN",
                                 hint="e.g. ax=AccX,ay=AccY,az=AccZ,gx=GyrX,gy=GyrY,gz=GyrZ")
            k, v = part.split("=", 1)
            if k.strip() in mapping:
                raise InputError(f"--columns: {k.strip()!r} given twice")
            mapping[k.strip()] = v.strip()
        src = None
    mapping = _canonical_keys(mapping, src)
    bad = [k for k in mapping if k not in REQUIRED + OPTIONAL]
    if bad or not any(k in mapping for k in REQUIRED):
        raise InputError(f"--columns: unknown keys {bad}" if bad else "--columns: no sensor column", src,
                         hint=f"keys: {', '.join(REQUIRED + OPTIONAL)} (at least one sensor column; "
                              "a sensor column left out is stored as NaN, e.g. a gyro-only capture "
                              "for rigctl allan)")
    return mapping


def _canonical_keys(mapping: dict[str, str], src: Any) -> dict[str, str]:
    """The column map with each sensor key in its one spelling (acc_x, gyr_x, accel_x, gyro_x
    -> ax, gx: rigctl.sensor_axes.canonical); an axis given under two spellings is refused."""
    out: dict[str, str] = {}
    for k, v in mapping.items():
        key = canonical(k) or k
        if key in out:
            raise InputError(f"--columns: axis {key} given twice ({k!r} is another spelling of it)", src)
        out[key] = v
    return out


def parse_units(text: str, needed: tuple[str, ...] = ("acc", "gyr")) -> dict[str, float]:
    """SI factor per sensor from ``acc=...,gyr=...,time=...`` (see the module docstring)."""
    out = {"acc": 1.0, "gyr": 1.0, "time": 1.0}
    given = set()
    for part in filter(None, (s.strip() for s in text.split(","))):
        if "=" not in part:
            raise InputError(f"--units: {part!r} is not SENSOR=UNIT", hint="e.g. acc=g,gyr=deg/s")
        k, v = (s.strip() for s in part.split("=", 1))
        if k not in out:
            raise InputError(f"--units: unknown sensor {k!r}", hint="use acc, gyr or time")
        m = re.fullmatch(r"counts?:\s*([0-9.eE+-]+)(?:\s*/\s*([0-9.eE+-]+))?\s*(.+)", v)
        try:
            if m:
                scale = float(m.group(1)) / (float(m.group(2)) if m.group(2) else 1.0)
                unit = m.group(3).strip()
            else:
                scale, unit = 1.0, v
            if unit in INCREMENT_UNITS.get(k, {}):
                out[k] = scale * INCREMENT_UNITS[k][unit]
                out[f"{k}_increment"] = 1.0
            else:
                out[k] = scale * UNIT_FACTORS[k][unit]
        except (KeyError, ValueError, ZeroDivisionError):
            raise InputError(f"--units: {part!r} not understood",
                             hint=f"{k} units: {', '.join([*UNIT_FACTORS[k], *INCREMENT_UNITS.get(k, {})])}, or counts:SCALE UNIT "
                                  "(e.g. counts:1/2048 g)") from None
        given.add(k)
    for k in needed:
        if k not in given:
            raise InputError(f"--units: give the {k} unit", hint="e.g. acc=g,gyr=deg/s or acc=counts:1/2048 g")
    return out


#: the column header of a Stable32 result file ("#  AF   Tau   #   Alpha  Min Sigma ...")
_STABLE32_RESULT = re.compile(r"\s*#\s*AF\s+Tau\s+#\s+Alpha\b")
#: a Stable32 data file's header lines (``# Type: Phase``, ``# Tau: 2.500000e+00``)
_STABLE32_HEADER = re.compile(r"\s*#\s*(Type|Tau)\s*:\s*(\S+)", re.IGNORECASE)


def stable32_header(path: Path) -> dict[str, str]:
    """``{"type": "phase"|"freq"|..., "tau": "2.5e+00"}`` from the ``#`` header of a Stable32
    data file (its first 4 kB; gzip read decompressed), lower-case keys; {} for any other file
    or one that cannot be read (read_table then says why)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
        if head[:2] == b"\x1f\x8b":
            with gzip.open(path, "rb") as fh:
                head = fh.read(4096)
        text = head.decode("utf-8-sig", errors="replace")
    except (OSError, EOFError, zlib.error):
        return {}
    out: dict[str, str] = {}
    for line in text.splitlines()[:40]:
        m = _STABLE32_HEADER.match(line)
        if m:
            out.setdefault(m.group(1).lower(), m.group(2))
    return out


def stable32_tau(header: dict[str, str]) -> float:
    """The sample interval a Stable32 header's ``Tau:`` line gives, s; NaN without one."""
    try:
        return float(header["tau"])
    except (KeyError, ValueError):
        return math.nan


def stable32_notes(header: dict[str, str], rate: float | None, integrated: bool,
                   time_column: bool) -> list[str]:
    """Warnings where the options disagree with a Stable32 data file's own header: ``Type:
    Phase`` without --integrated (the time error would be taken for a rate), ``Type: Freq``
    with it, and --rate other than 1 / ``Tau`` (without a time column). Empty otherwise."""
    out = []
    kind = header.get("type", "").lower()
    if kind.startswith("phase") and not integrated:
        out.append("warning: the file's header says Type: Phase (time error, s): without "
                   "--integrated and --units gyr=rad its values were taken as rates; phase data: "
                   "--units gyr=rad --integrated")
    if kind.startswith("freq") and integrated:
        out.append("warning: the file's header says Type: Freq (fractional frequency, a rate): "
                   "--integrated differenced it as if it were phase; frequency data: --units "
                   "gyr=rad/s without --integrated")
    tau = stable32_tau(header)
    if rate is not None and not time_column and tau > 0 and abs(rate * tau - 1.0) > 1e-6:
        out.append(f"warning: the file's header says Tau: {tau:g} s (--rate {1.0 / tau:.8g}); "
                   f"--rate {rate:g} was given")
    return out


#: separators tried in this order on the first data line (else runs of whitespace)
DELIMITERS = (",", "\t", ";")


def _split_rows(path: Path, skip_rows: int) -> tuple[list[list[str]], str, int]:
    """The lines of a text table split into fields: comma-, tab- or semicolon-separated (the
    first line after ``skip_rows`` and any ``#``/``%`` comment lines decides), else runs of
    whitespace. Returns (rows, delimiter name, number of lines before the rows). A gzip file
    (by its first bytes, e.g. LOG.csv.gz) is read decompressed."""
    try:
        raw = path.read_bytes()
        if raw[:2] == b"\x1f\x8b":
            raw = gzip.decompress(raw)
        text = raw.decode("utf-8-sig")
    except (gzip.BadGzipFile, EOFError, zlib.error) as exc:
        raise InputError(f"a damaged gzip file ({exc})", path) from None
    except UnicodeDecodeError:
        raise InputError("not a UTF-8 text table (CSV, TSV or whitespace-separated columns)", path,
                         hint="give the log as text, or a ROS bag / MCAP file") from None
    except OSError as exc:
        raise InputError(f"cannot be read ({exc})", path) from None
    if "\0" in text[:4096]:
        raise InputError("a binary file, not a text table (CSV, TSV or whitespace-separated columns)",
                         path, hint="give the log as text, or a ROS bag / MCAP file")
    lines = text.splitlines()
    first = skip_rows
    while first < len(lines) and (not lines[first].strip() or lines[first].lstrip()[:1] in ("#", "%")):
        first += 1
    if first >= len(lines):
        raise InputError(f"no table: {len(lines)} lines, all comments or blank after --skip-rows {skip_rows}",
                         path)
    if any(_STABLE32_RESULT.match(ln) for ln in lines[:first]):
        raise InputError("a Stable32 result table (averaging factor, tau, deviation per line), not samples",
                         path, hint="rigctl import takes the phase or frequency data the table was computed "
                                    "from (e.g. --columns gx=0 --units gyr=rad --integrated --rate 1 for "
                                    "phase in s); rigctl allan then computes the deviations")
    probe = lines[first: first + 2]
    # semicolons on every probed line first: a European export separates with ';' because its
    # numbers carry a decimal comma (1,5;0,25), and commas would split those numbers
    order = (";", *DELIMITERS) if all(";" in ln for ln in probe) else DELIMITERS
    delim = next((d for d in order if all(d in ln for ln in probe)), None)
    if delim is None:
        rows = [ln.split() for ln in lines[first:]]
        name = "whitespace"
    elif '"' not in text and "\0" not in text and max(map(len, lines[first:])) <= csv.field_size_limit():
        # without a quote character, a NUL or a line over the csv module's field limit,
        # csv.reader's fields are the line split at the delimiter (an empty line: no field)
        rows = [ln.split(delim) if ln else [] for ln in lines[first:]]
        name = {",": "comma", "\t": "tab", ";": "semicolon"}[delim]
    else:
        try:
            rows = list(csv.reader(lines[first:], delimiter=delim))
        except csv.Error as exc:
            raise InputError(f"cannot be read as a table ({exc})", path) from None
        name = {",": "comma", "\t": "tab", ";": "semicolon"}[delim]
    return rows, name, first


#: a number written with a decimal comma (1,5 / -0,25e-3), as European spreadsheets export
_DECIMAL_COMMA = re.compile(r"[+-]?(\d+,\d*|,\d+)([eE][+-]?\d+)?")


def read_table(path: Path, mapping: dict[str, str], skip_rows: int,
               notes: list[str] | None = None) -> tuple[dict[str, np.ndarray], int]:
    """Columns of a text table (CSV, TSV, semicolon or whitespace-separated; a header line or
    none; ``#``/``%`` comment lines before it skipped) as arrays (sensor/time/temp float,
    section str); the line number of the first data row.

    Also read as a stranger's export writes them (each said in ``notes``): a units line right
    after the header (every mapped field in it not a number: skipped), numbers with a decimal
    comma in a semicolon-, tab- or whitespace-separated table, and a time column of ISO 8601
    date-times (``2015-08-20 23:58:30.25``, ``...T...Z``), returned as int64 nanoseconds under
    ``time`` with ``time_is_datetime`` set."""
    notes = [] if notes is None else notes
    if not path.is_file():
        raise InputError("input file not found", path)
    rows, delim, first = _split_rows(path, skip_rows)
    header_line = first + 1
    header = [h.strip() for h in rows[0]]
    numeric_header = all(_is_number(h) or _DECIMAL_COMMA.fullmatch(h) or _datetime_ns(h) is not None
                         for h in header if h)
    body = rows if numeric_header else rows[1:]
    first_data_line = header_line if numeric_header else header_line + 1
    index: dict[str, int] = {}
    for key, col in mapping.items():
        if col.isdigit() and (numeric_header or col not in header):
            index[key] = int(col)
            if index[key] >= len(header):
                raise InputError(f"column {col} (for {key}) does not exist: the first line has "
                                 f"{len(header)} {delim}-separated fields (0..{len(header) - 1})",
                                 path, header_line, hint="column numbers count from 0")
        elif col in header:
            index[key] = header.index(col)
        else:
            names = {c for c in mapping.values() if not c.isdigit()}
            found = next((k for k, r in enumerate(rows[:200]) if names <= {c.strip() for c in r}), None)
            hint = (f"line {header_line + found} holds every named column: give --skip-rows "
                    f"{first + found}"
                    if found else "fix --columns (header names, or 0-based numbers for a file without "
                    "a header), or --skip-rows so the header line is read")
            raise InputError(f"column {col!r} (for {key}) is not in the header {header}", path, header_line,
                             hint=hint)
    out: dict[str, np.ndarray] = {}
    # a row with a field that is not blank (its fields joined: the same test as any field's
    # strip() being non-empty, one call per row) and not a comment
    keep = [k for k, r in enumerate(body) if "".join(r).strip()
            and not r[0].lstrip().startswith(("#", "%"))]
    if not numeric_header and len(keep) > 1:  # a units line under the header (s, deg/s, g, ...)
        r0 = body[keep[0]]
        fields = [r0[j].strip() if j < len(r0) else "" for k, j in index.items() if k != "section"]
        if fields and not any(_is_number(v) or _DECIMAL_COMMA.fullmatch(v) or _datetime_ns(v) is not None
                              for v in fields):
            notes.append(f"line {first_data_line + keep[0]} ({', '.join(repr(v) for v in fields)}) has no "
                         "number in the columns read: taken for a units line under the header and skipped "
                         "(the units are those of --units)")
            keep = keep[1:]
    body = [body[k] for k in keep]
    if not body:
        raise InputError("no data rows", path, first_data_line)
    comma = delim != "comma" and any(
        _DECIMAL_COMMA.fullmatch(body[0][j].strip()) for k, j in index.items()
        if k != "section" and j < len(body[0]))
    if comma:
        body = [[c.replace(",", ".") if _DECIMAL_COMMA.fullmatch(c.strip()) else c for c in r] for r in body]
        notes.append("numbers with a decimal comma: the comma read as the decimal point")
    for key, j in index.items():
        if key == "section":
            out[key] = np.array([r[j].strip() if j < len(r) else "" for r in body])
            continue
        if key == "time":  # integer stamps (ns since 1970: beyond float64's 2^53) kept exact
            try:
                out[key] = np.array([r[j] for r in body], dtype=np.int64)
                continue
            except (ValueError, IndexError, OverflowError):
                pass
            exact = _epoch_seconds([r[j] if j < len(r) else "" for r in body])
            if exact is not None:  # seconds since 1970 with a decimal fraction, kept exact
                out[key], out["time_origin"] = exact  # (the stamps = origin + these)
                continue
            if j < len(body[0]) and not _is_number(body[0][j]) and _datetime_ns(body[0][j]) is not None:
                ns = np.empty(len(body), dtype=np.int64)
                for n, r in enumerate(body):
                    v = _datetime_ns(r[j]) if j < len(r) else None
                    if v is None:
                        got = r[j] if j < len(r) else "(missing)"
                        raise InputError(f"column {mapping[key]!r}: {got!r} is not a date-time like the "
                                         f"first row's {body[0][j]!r}", path, first_data_line + keep[n],
                                         hint="fix or remove the row") from None
                    ns[n] = v
                out[key] = ns
                out["time_is_datetime"] = np.array(True)
                notes.append(f"time column {mapping[key]!r}: ISO 8601 date-times (first "
                             f"{body[0][j].strip()!r}), read to the nanosecond; a date-time without a "
                             "zone is taken as UTC")
                continue
        try:  # the common case at once; the row-by-row pass below only to name a bad row
            vals = np.array([r[j] for r in body], dtype=np.float64)
            if np.isfinite(vals).all():
                out[key] = vals
                continue
        except (ValueError, IndexError):
            pass
        vals = np.empty(len(body))
        for n, r in enumerate(body):
            try:
                vals[n] = float(r[j])
                if not math.isfinite(vals[n]):
                    raise ValueError
            except (ValueError, IndexError):
                got = r[j] if j < len(r) else "(missing)"
                raise InputError(f"column {mapping[key]!r}: {got!r} is not a number", path,
                                 first_data_line + keep[n], hint="fix or remove the row, or adjust --skip-rows") from None
        out[key] = vals
    return out, first_data_line


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


_DECIMAL_STAMP = re.compile(r"\s*(\d+)\.(\d*)\s*")


def _epoch_seconds(values: list[str]) -> tuple[np.ndarray, np.ndarray] | None:
    """Decimal time stamps of 1000 units and more (seconds since 1970 with a fraction, as loggers
    and ROS CSV exports write them; a Stable32 file's MJD days) relative to the first's integer
    part, from their integer and fraction parts: exact where float64 of the whole stamp is not
    (1.7e9 s holds only ~0.2 us, MJD 53000 d only ~1 us: the steps, and the rate from their
    median, came out wrong in the 7th digit); with that integer part (int64: the stamps are
    it plus the values). None for anything else."""
    first = _DECIMAL_STAMP.fullmatch(values[0]) if values else None
    if first is None or len(first.group(1).lstrip("0")) < 4:
        return None
    ints = np.empty(len(values), dtype=np.int64)
    fracs = np.empty(len(values))
    for n, v in enumerate(values):
        m = _DECIMAL_STAMP.fullmatch(v)
        if m is None:
            return None
        ints[n] = int(m.group(1))
        fracs[n] = float("0." + (m.group(2) or "0"))
    return (ints - ints[0]).astype(np.float64) + fracs, np.array(ints[0], dtype=np.int64)


_ISO_DATETIME = re.compile(r"\s*(\d{4}-\d{2}-\d{2})[T ](\d{2}:\d{2}(?::\d{2})?)(?:[.,](\d+))?"
                           r"\s*(Z|[+-]\d{2}:?\d{2})?\s*")


def _datetime_ns(s: str) -> int | None:
    """Nanoseconds since 1970 of an ISO 8601 date-time (``YYYY-MM-DD[T ]HH:MM[:SS[.f...]][Z|+HH:MM]``,
    no zone = UTC; the fraction kept to the nanosecond), else None."""
    import datetime as dt

    m = _ISO_DATETIME.fullmatch(s)
    if not m:
        return None
    zone = m.group(4) or "+00:00"
    zone = "+00:00" if zone == "Z" else (zone if ":" in zone else zone[:3] + ":" + zone[3:])
    try:
        whole = dt.datetime.fromisoformat(f"{m.group(1)}T{m.group(2)}{zone}")
    except ValueError:
        return None
    frac = (m.group(3) or "")[:9].ljust(9, "0")
    epoch = dt.datetime(1970, 1, 1, tzinfo=dt.timezone.utc)
    delta = whole - epoch
    return (delta.days * 86400 + delta.seconds) * 1_000_000_000 + int(frac)


def sections_from_json(path: Path, n: int) -> list[dict[str, Any]]:
    """Sections from an imucal-style {"label": {"start", "end"}} or a list of dicts."""
    if not path.is_file():
        raise InputError("segments file not found", path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON ({exc.msg})", path, exc.lineno) from None
    items = ([{"label": k, **v} for k, v in data.items()] if isinstance(data, dict) else data)
    out = []
    for it in items:
        try:
            s, e = int(it["start"]), int(it["end"])
        except (KeyError, TypeError, ValueError):
            raise InputError(f"section {it!r} needs integer start and end", path,
                             hint="sample indices, end exclusive") from None
        if not 0 <= s < e <= n:
            raise InputError(f"section {it.get('label')!r}: [{s}, {e}) outside the {n} samples", path)
        out.append({"label": str(it.get("label", f"section {len(out)}")), "start": s, "end": e,
                    "kind": it.get("kind")})
    return sorted(out, key=lambda d: d["start"])


def sections_from_column(labels: np.ndarray) -> list[dict[str, Any]]:
    """Runs of equal non-empty labels."""
    out = []
    edges = np.flatnonzero(labels[1:] != labels[:-1]) + 1
    for s, e in zip(np.r_[0, edges], np.r_[edges, len(labels)]):
        if labels[s]:
            out.append({"label": str(labels[s]), "start": int(s), "end": int(e), "kind": None})
    return out


def _is_static(acc: np.ndarray, gyr: np.ndarray, ref_noise: float) -> bool:
    """At rest: the gyro magnitude's spread is of the order of the quietest section's."""
    return bool(np.linalg.norm(gyr.std(axis=0)) < 10.0 * ref_noise)


#: first-stamp range read as wall-clock (Unix) time: 1990-01-01 .. 2100-01-01 UTC, ns; outside it
#: (a sensor's or a computer's time since boot) the recording keeps the import's own times
_WALL_CLOCK_NS = (631_152_000 * 10**9, 4_102_444_800 * 10**9)


#: a capture read as ending later than this after the import is not dated by its stamps, s
FUTURE_SLACK_S = 86400.0


def _wall_clock_span(stamp_zero_ns: int, duration_s: float) -> tuple[str, str] | None:
    """(started_utc, ended_utc) of a capture whose first stamp is ``stamp_zero_ns`` (ns since
    the Unix epoch) and which lasts ``duration_s``, as the recorder writes times; None when the
    stamp is not a wall-clock time (see _WALL_CLOCK_NS) or the capture would end after the
    import (more than FUTURE_SLACK_S later: a clock-zone slip is allowed, a future is not).
    The second rule catches seconds counted from another epoch: a Stable32 or NTP time tag of
    2016 (seconds since 1900, 3.66e9) read as Unix seconds is a date in 2086."""
    import datetime as _dt

    if not _WALL_CLOCK_NS[0] <= int(stamp_zero_ns) < _WALL_CLOCK_NS[1]:
        return None
    t0 = _dt.datetime(1970, 1, 1, tzinfo=_dt.timezone.utc) + _dt.timedelta(
        microseconds=int(stamp_zero_ns) // 1000)
    t1 = t0 + _dt.timedelta(seconds=float(duration_s))
    now = _dt.datetime.now(_dt.timezone.utc)
    if (t1 - now).total_seconds() > FUTURE_SLACK_S:
        return None
    iso = "%Y-%m-%dT%H:%M:%S.%fZ"
    return t0.strftime(iso), t1.strftime(iso)


#: /meta capture_time: where started_utc / ended_utc of an imported recording come from
CAPTURE_TIME_STAMPS = "the file's own time stamps (wall clock)"
CAPTURE_TIME_UNKNOWN = ("unknown: the file has no wall-clock time stamps; started_utc and ended_utc "
                        "are the import's own time")


def csv_stamp_zero_ns(cols: dict[str, np.ndarray], factor_s: float) -> int | None:
    """The first row's time stamp in ns since 1970 when the CSV's time column holds absolute
    stamps (ISO 8601 date-times, integer or decimal counts of ``factor_s`` seconds since 1970),
    else None (no time column). Whether it is a wall-clock time is _wall_clock_span's call."""
    if "time" not in cols or not len(cols["time"]):
        return None
    if "time_is_datetime" in cols:  # int64 ns since 1970
        return int(cols["time"][0])
    first = cols["time"][0]
    k = factor_s * 1e9  # ns per unit: whole for every unit --units names (s .. d, ns: 1)

    def whole_ns(v: int) -> int:  # an integer count of units in ns, exactly where it can be
        return int(v) * int(round(k)) if abs(k - round(k)) < 1e-6 else int(round(int(v) * k))

    if "time_origin" in cols:  # decimal stamps: the integer part of the first + its fraction
        return whole_ns(int(cols["time_origin"])) + int(round(float(first) * k))
    if np.issubdtype(np.asarray(cols["time"]).dtype, np.integer):
        return whole_ns(int(first))
    return int(round(float(first) * k)) if math.isfinite(float(first)) else None


def write_recording(out: Path, t: np.ndarray, acc: np.ndarray, gyr: np.ndarray, temp: np.ndarray,
                    rate: float, sections: list[dict[str, Any]], meta: dict[str, Any],
                    counter: np.ndarray | None = None, note: str = "",
                    ended_utc: str | None = None) -> None:
    """A complete recording (docs/data-format.md) through rigctl.recording.recorder.Recorder: the one
    writer of every import. ``counter`` (uint64; default 0..n-1) carries dropped samples as
    jumps; ``note`` is added to the import event's message. ``ended_utc`` (with ``meta``'s
    ``started_utc``): the capture's own end, written over the recorder's closing time. Either
    way the import's own time is kept in ``import_utc`` and ``capture_time`` says which the
    recording's times are (CAPTURE_TIME_STAMPS with ``ended_utc``, else CAPTURE_TIME_UNKNOWN)."""
    from ..recording.recorder import Recorder, Segment

    n = len(t)
    counter = np.arange(n, dtype=np.uint64) if counter is None else np.asarray(counter, np.uint64)
    rec = Recorder(out, meta, None, imu_rate_hz=rate)
    try:
        step = 1 << 16
        for a in range(0, n, step):
            z = min(n, a + step)
            rec.append_imu(ImuBlock(time=t[a:z], counter=counter[a:z], specific_force=acc[a:z],
                                    angular_rate=gyr[a:z], temperature=temp[a:z]))
        for k, s in enumerate(sections):
            rec.add_segment(Segment(kind=s["kind"], label=s["label"][:48], step=k, first_sample=s["start"],
                                    last_sample=s["end"], t_start=float(t[s["start"]]),
                                    t_end=float(t[s["end"] - 1]), settle_time=0.0, commanded_angle=NAN3,
                                    commanded_rate=NAN3, measured_angle=NAN3, measured_rate=NAN3),
                            file_time=True, flush=False)
        rec.add_event(0.0, "import", f"imported from {meta['import_source']}" + (f"; {note}" if note else ""),
                      file_time=True)
    except BaseException:
        rec.close("failed")
        raise
    rec.close("complete")
    import h5py

    with h5py.File(out, "r+") as f:
        f["meta"].attrs["import_utc"] = f["meta"].attrs["ended_utc"]
        if ended_utc is not None:
            f["meta"].attrs["ended_utc"] = ended_utc
        f["meta"].attrs["capture_time"] = CAPTURE_TIME_STAMPS if ended_utc is not None else CAPTURE_TIME_UNKNOWN


def check_output(src: Path, out: Path, force: bool) -> None:
    """Refuse to overwrite (without ``force``), to replace a directory or the input, or to
    write into a directory that does not exist."""
    if out.is_dir():
        raise InputError("-o is a directory", out, hint="give -o the path of the file to write (.h5)")
    if out.exists() and not force:
        raise InputError("output exists", out, hint="choose another -o or pass --force to replace it")
    if out.resolve() == src.resolve():
        raise InputError("the output would replace the input", out, hint="choose another -o")
    if not out.parent.is_dir():
        raise InputError("output directory does not exist", out.parent)


def check_plausible(src: Path, mapping: dict[str, str], acc: np.ndarray, gyr: np.ndarray,
                    units: str | None, gyr_increment: bool = False, acc_increment: bool = False) -> None:
    """InputError naming the column when a converted sensor value is beyond what any IMU
    outputs (:data:`rigctl.recording.recording_reader.PLAUSIBLE`, SI): a unit or scale error, e.g. a
    frequency counter's 10 MHz readings taken as rad/s. Refused here, at the import, with the
    value and the way to scale it, rather than by ``rigctl allan`` later."""
    for sensor, data, key, unit, incr in (("gyr", gyr, "imu/angular_rate", "rad/s", gyr_increment),
                                          ("acc", acc, "imu/specific_force", "m/s^2", acc_increment)):
        limit = PLAUSIBLE[key]
        if incr:  # increments are divided by the sample interval later: compare per sample
            continue
        with np.errstate(invalid="ignore"):
            big = np.abs(data) > limit
        if not big.any():
            continue
        row, c = (int(v[0]) for v in np.nonzero(big))
        name = axis_name("gyro" if sensor == "gyr" else "accel", c)
        share = float(big[:, c].mean())
        raise InputError(
            f"column {mapping.get(name, name)!r} ({name}) reads {data[row, c]:.6g} {unit} at data row "
            f"{row + 1} with --units {units!r} ({share:.0%} of its rows beyond +-{limit:g} {unit}): not an "
            "IMU's output", src,
            hint=f"check the unit, or give the column's scale: --units '{sensor}=counts:SCALE UNIT' "
                 f"(e.g. a counter's 10 MHz frequency readings as fractional frequency: "
                 f"'{sensor}=counts:1e-7 {'rad/s' if sensor == 'gyr' else 'm/s^2'}')")


def check_ranges(args: ImportOptions) -> None:
    """The numeric options shared by every input, each inside its range (NaN fails)."""
    for opt, v, lo, hi in (("--gravity", args.gravity, 9.7, 9.9), ("--latitude-deg", args.latitude_deg, -90, 90),
                           ("--t-init", args.t_init, 0.0, 1e6), ("--skip-rows", args.skip_rows, 0, 1e9)):
        if v is not None and not lo <= v <= hi:  # NaN fails too
            raise InputError(f"{opt} {v:g} is outside [{lo:g}, {hi:g}]")


def find_sections(args: ImportOptions, src: Path, acc: np.ndarray, gyr: np.ndarray, rate: float,
                  labels: np.ndarray | None = None, label_column: str = "") -> tuple[list[dict[str, Any]], str]:
    """Sections (``--segments`` JSON, else a section column's ``labels``, else automatic static
    detection) with their kinds, and a description of where they came from."""
    n = len(acc)
    if args.segments:
        sections = sections_from_json(Path(args.segments), n)
        origin = f"sections file {args.segments}"
    elif labels is not None:
        sections = sections_from_column(labels)
        origin = f"section column {label_column!r}"
    else:
        from ..solvers.multipos import detect_static_intervals

        try:
            iv = detect_static_intervals(acc, float(rate), args.t_init)
        except ValueError as exc:
            raise InputError(f"automatic static-interval detection: {exc}", src,
                             hint="give --t-init SECONDS of initial rest, or --segments JSON") from None
        sections = [{"label": "initial rest" if k == 0 else f"pose {k}", "start": s, "end": e,
                     "kind": "orientation"} for k, (s, e) in enumerate(iv)]
        origin = f"automatic static-interval detection (t_init {args.t_init:g} s, Tedaldi et al. 2014)"
    if not sections:
        raise InputError("no sections found", src, hint="give --segments JSON or check --t-init")
    quiet = min(np.linalg.norm(gyr[s["start"]:s["end"]].std(axis=0)) for s in sections)
    for s in sections:
        if s["kind"] is None:
            moving = "rot" in s["label"].lower() or not _is_static(acc[s["start"]:s["end"]],
                                                                   gyr[s["start"]:s["end"]], quiet)
            s["kind"] = "capture" if moving else "orientation"
    return sections, origin


def import_meta(args: ImportOptions, src: Path, rate: float, origin: str,
                extra: dict[str, Any]) -> dict[str, Any]:
    """/meta of an imported recording: site gravity, provenance, no unit identity
    (docs/data-format.md); ``extra`` holds the input-specific ``import_*`` keys."""
    lat = args.latitude_deg
    g = args.gravity if args.gravity is not None else (normal_gravity(math.radians(lat), 0.0)
                                                       if lat is not None else G0)
    return {"procedure_name": "import", "procedure_text": "", "config_yaml": "",
            "versions_json": json.dumps({"rigctl": __version__}),
            "latitude_deg": float("nan") if lat is None else float(lat), "height_m": 0.0,
            "gravity_m_s2": float(g), "import_source": str(src), **extra,
            "import_rate_hz": float(rate), "import_sections": origin, "orientation_free": 1,
            # the unit under test is unknown to an imported log (docs/data-format.md, /meta)
            "imu_device_id": "", "imu_serial": "",
            "imu_identity_json": json.dumps({"device_id": "", "protocol": ""}, sort_keys=True),
            "rig": "none: imported log (no table; segment orientations unknown)"}


@dataclass
class Imported:
    """What an import wrote: output, samples, sample rate (Hz), sections, lines to print."""

    out: Path
    n: int
    rate_hz: float
    sections: list[dict[str, Any]]
    lines: list[str]
    messages: int = 0  # messages read (bags)


CSV_ONLY = ("columns", "units", "rate", "integrated")
BAG_ONLY = ("topic",)


def _binary(src: Path) -> bool:
    """Binary data, not a text table: a NUL byte in the first 4 kB of a file that is not gzip
    (read_table's rule, there on the decompressed text). Said as such, not as a CSV file
    lacking --columns (a PNG given to `rigctl import` was)."""
    with open(src, "rb") as fh:
        head = fh.read(4096)
    return b"\x00" in head and not head.startswith(b"\x1f\x8b")


def stamp_rate(dt: np.ndarray) -> float:
    """The sample rate a time column gives, Hz, from its steps ``dt`` (s, all > 0): the number
    of sample intervals over the stamps' span, rate = sum(k) / sum(dt), where k = max(1,
    rint(dt / d1)) counts each step's intervals (k - 1 dropped samples: the gap rule) and d1
    is the mean of the steps that are not gaps (at most 1.75 x the median step).

    Not the median step: stamps rounded to a clock's tick take only a few values, and the
    median is one of them -- a 400 Hz IMU stamped in whole milliseconds steps 2, 3, 2, 3 ms,
    whose median (2 ms) said 500 Hz, 25 % off, and every tau with it; 99.987 Hz stamped to
    1 us gave 99.990001. The span of n stamps is read to one tick over (n - 1) intervals.
    The 1.75 keeps the long steps of a rounded cadence (3 ms against a median of 2) in d1 and
    a step of two intervals (a dropped sample) out of it."""
    d_med = float(np.median(dt))
    regular = dt <= 1.75 * d_med
    d1 = float(np.mean(dt[regular]))
    k = np.maximum(1.0, np.rint(dt / d1))
    return float(k.sum() / dt.sum())


#: a time column whose steps are gaps (longer than 1.5 intervals) more often than this is not
#: "one interval with occasional drops", and the import says so (cadence_warnings)
GAP_STEP_SHARE = 0.05


def cadence_warnings(dt: np.ndarray, rate: float, given: bool) -> list[str]:
    """Warnings on a time column that the gap rule (a step of k intervals = k - 1 dropped
    samples, k = rint(step * rate)) would misread. ``dt``: the steps, s; ``rate``: the sample
    rate the import uses, Hz (``given``: by --rate, else :func:`stamp_rate`).

    Two cases: (1) more than GAP_STEP_SHARE of the steps are gaps -- an instrument reporting
    in a cycle (a clock comparison's three 1.3-s readings then a 6.6-s pause, a Stable32
    data file whose Tau is the cycle's mean), whose "gaps" would leave Allan stretches of a few
    samples and a curve of two taus; (2) with --rate, steps shorter than half its interval
    (rint gives 0: two samples in one interval, counted as consecutive). Each: one line naming
    the counts, the median and mean step, and the way to import the samples as equally spaced
    (no time column, --rate 1 / mean step) when the instrument's own time base is regular."""
    if dt.size == 0:
        return []
    k = np.rint(dt * rate)
    gaps = int(np.count_nonzero(k > 1))
    short = int(np.count_nonzero(k < 1)) if given else 0
    out = []
    fix = (f"median step {np.median(dt):.6g} s, mean {np.mean(dt):.6g} s; if the instrument's "
           "samples are equally spaced in its own time base (a counter's gate, a clock "
           "comparison's cycle, a Stable32 data file's Tau), import without time= in --columns "
           f"and give --rate (1 / mean step = {format_rate(1.0 / float(np.mean(dt)))})")
    if gaps > GAP_STEP_SHARE * dt.size:
        out.append(f"warning: {gaps} of {dt.size} steps of the time column "
                   f"({100.0 * gaps / dt.size:.0f} %) are longer than 1.5 intervals of "
                   f"{format_rate(rate)} and were taken as gaps: not one interval with occasional drops "
                   f"but an irregular cadence ({fix})")
    if short:
        out.append(f"warning: {short} of {dt.size} steps of the time column are shorter than "
                   f"half the interval of --rate {format_rate(rate)} (two samples in one interval, "
                   f"counted as consecutive) ({fix})")
    return out


def import_csv(args: ImportOptions) -> Imported:
    """Read, convert and write a CSV log."""
    src = Path(args.file)
    out = Path(args.output)
    if not src.is_file():
        raise InputError("input file not found", src)
    for opt in BAG_ONLY:
        if getattr(args, opt) is not None:
            raise InputError(f"--{opt} applies to ROS bags and MCAP files only", src)
    if _binary(src):  # as read_table says it, before asking for --columns
        raise InputError("a binary file, not a text table (CSV, TSV or whitespace-separated columns)",
                         src, hint="give the log as text, or a ROS bag / MCAP file")
    for opt in ("columns", "units"):
        if not getattr(args, opt):
            raise InputError(f"--{opt} is required for a CSV file", src,
                             hint="e.g. --columns ax=AccX,...,gz=GyrZ --units acc=g,gyr=deg/s; a ROS bag or MCAP file needs neither")
    check_output(src, out, args.force)
    mapping = parse_columns(args.columns)
    present = tuple(k for k, names in (("acc", ACCEL_AXES), ("gyr", GYRO_AXES)) if any(a in mapping for a in names))
    factors = parse_units(args.units, present)
    if args.rate is not None and not 0 < args.rate <= MAX_RATE_HZ:
        raise InputError(f"--rate {args.rate:g} is outside (0, {MAX_RATE_HZ:g}] Hz", src)
    header = stable32_header(src)
    if args.rate is None and "time" not in mapping:
        tau = stable32_tau(header)
        raise InputError("--rate HZ is required without a time column (time= in --columns)", src,
                         hint=(f"the file's Stable32 header says Tau: {tau:g} s: --rate {1.0 / tau:.8g}"
                               if tau > 0 else "give the nominal sample rate, e.g. --rate 100"))
    check_ranges(args)
    lines: list[str] = []
    cols, first_line = read_table(src, mapping, args.skip_rows, lines)
    n = next(len(v) for k, v in cols.items() if k in REQUIRED)
    nan = np.full(n, np.nan)
    acc = np.column_stack([cols.get(k, nan) for k in REQUIRED[:3]]) * factors["acc"]
    gyr = np.column_stack([cols.get(k, nan) for k in REQUIRED[3:]]) * factors["gyr"]
    check_plausible(src, mapping, acc, gyr, args.units, bool(factors.get("gyr_increment")),
                    bool(factors.get("acc_increment")))
    counter = None
    if "time" in cols:
        if "time_is_datetime" in cols:  # int64 ns since 1970, whatever --units says of time
            if "time=" in (args.units or "").replace(" ", "") and factors["time"] != 1e-9:
                lines.append("--units time= does not apply to a date-time column (read in ns)")
            factors["time"] = 1e-9
        t = (cols["time"] - cols["time"][0]).astype(np.float64) * factors["time"]
        dt = np.diff(t)
        if np.any(dt <= 0):
            k = int(np.flatnonzero(dt <= 0)[0])
            raise InputError(f"time column not increasing at data row {k + 2} (line "
                             f"{first_line + k + 1})", src,
                             hint="fix the time column or drop time= from --columns (then --rate)")
        if n < 2:
            raise InputError("one data row: no sample rate", src)
        rate = float(args.rate) if args.rate is not None else stamp_rate(dt)
        if not 0 < rate <= MAX_RATE_HZ:
            raise InputError(f"the time column gives {rate:g} Hz, outside (0, {MAX_RATE_HZ:g}]", src,
                             hint="check the time unit (--units time=s|ms|us|ns|min|h|d)")
        # dropped samples: steps longer than 1.5 intervals become /imu/counter jumps
        counter = np.concatenate(([0], np.cumsum(np.maximum(1, np.rint(dt * rate))))).astype(np.uint64)
        missing = int(counter[-1]) + 1 - n
        lines.append(f"sample rate {format_rate(rate)} ({'given' if args.rate is not None else 'the time column: its intervals over its span'}); "
                     + (f"{int((np.rint(dt * rate) > 1).sum())} gaps, {missing} samples missing "
                        "(/imu/counter jumps)" if missing else "no gaps"))
        lines.extend(cadence_warnings(dt, rate, args.rate is not None))
    else:
        rate = float(args.rate)
        t = np.arange(n) / rate
        lines.append(f"sample rate {format_rate(rate)} (given; no time column: sample k at t = k / rate)")
    lines.extend(stable32_notes(header, args.rate, bool(args.integrated), "time" in cols))
    temp = cols["temp"] if "temp" in cols else np.full(n, np.nan)
    incr = [k for k in ("acc", "gyr") if factors.get(f"{k}_increment")]
    if args.integrated and not incr:
        raise InputError("--integrated needs an angle or velocity unit (e.g. gyr=rad, acc=m/s): "
                         "the columns are then running integrals, differenced into rates", src)
    if incr:  # increments per sample (or their running sums) -> rates, SI
        steps = np.ones(n) if counter is None else np.diff(counter.astype(np.float64), prepend=-1.0)
        if args.integrated:
            if n < 3:
                raise InputError("--integrated needs at least 3 rows", src)
            if "acc" in incr:
                acc = np.diff(acc, axis=0)
            if "gyr" in incr:
                gyr = np.diff(gyr, axis=0)
            t, temp, steps = t[1:] - t[1], temp[1:], steps[1:]
            counter = None if counter is None else counter[1:] - counter[1]
            n -= 1
            if "acc" not in incr:
                acc = acc[1:]
            if "gyr" not in incr:
                gyr = gyr[1:]
        for k in incr:
            if k == "acc":
                acc = acc * (rate / steps)[:, None]
            else:
                gyr = gyr * (rate / steps)[:, None]
        lines.append(f"{' and '.join(incr)}: {'running integrals, differenced' if args.integrated else 'increments per sample'} "
                     f"and divided by the sample interval (1 / {format_rate(rate)}) into rates")
    absent = [k for k in REQUIRED if k not in mapping]
    if absent:
        axes = ",".join(k for k in REQUIRED if k in mapping)
        if args.segments:  # the user's sections (a capture each unless it says otherwise)
            sections = [{**s, "kind": s["kind"] or "capture"}
                        for s in sections_from_json(Path(args.segments), n)]
            origin = f"sections file {args.segments} (sensor columns missing: captures)"
        else:
            sections = [{"label": "whole record", "start": 0, "end": n, "kind": "capture"}]
            origin = "the whole record (sensor columns missing: no static-interval detection)"
        lines.append(f"not in the file, stored as NaN: {', '.join(absent)}; rigctl allan analyses "
                     f"the columns present ({axes})")
    else:
        axes = ""
        sections, origin = find_sections(args, src, acc, gyr, rate, cols.get("section"),
                                         mapping.get("section", ""))
    meta = import_meta(args, src, rate, origin,
                       {"import_format": "csv", "import_columns_json": json.dumps(mapping),
                        "import_units_json": json.dumps(args.units), "import_axes": axes})
    # dated by the file's own stamps where they are wall-clock times (as a bag's), else the
    # start is said to be unknown (/meta capture_time)
    zero_ns = csv_stamp_zero_ns(cols, factors["time"])
    if zero_ns is not None and args.integrated:  # the first row was differenced away
        zero_ns += int(round(float(cols["time"][1] - cols["time"][0]) * factors["time"] * 1e9))
    span = None if zero_ns is None else _wall_clock_span(zero_ns, float(t[-1]) if n else 0.0)
    if span is not None:
        meta["started_utc"] = span[0]
        meta["import_stamp_zero_ns"] = np.int64(zero_ns)
        meta["clock_zero_unix_s"] = zero_ns * 1e-9
        lines.append(f"dated by the time column: {span[0]} to {span[1]} (UTC)")
    elif zero_ns is not None and _WALL_CLOCK_NS[0] <= zero_ns < _WALL_CLOCK_NS[1]:
        lines.append("not dated by the time column: read as seconds since 1970 its stamps lie "
                     "after this import (another epoch? NTP and Stable32 time tags count from "
                     "1900); the capture's start is unknown (/meta capture_time; started_utc is "
                     "the import's own time)")
    else:
        lines.append("no wall-clock time stamps in the file: the capture's start is unknown "
                     "(/meta capture_time; started_utc is the import's own time)")
    write_recording(out, t, acc, gyr, temp, rate, sections, meta, counter=counter,
                    ended_utc=None if span is None else span[1])
    return Imported(out, n, rate, sections,
                    [f"imported {n} samples from {args.file}", *lines])


def import_bag(args: ImportOptions, progress: Progress | None = None) -> Imported:
    """Read one sensor_msgs/Imu topic of a ROS bag, rosbag2 directory or MCAP file
    (rigctl.analysis.bag_import) and write it."""
    src = Path(args.file)
    out = Path(args.output)
    for opt in CSV_ONLY:
        if getattr(args, opt):
            raise InputError(f"--{opt} applies to CSV files only: a bag's Imu messages are in SI "
                             "units and carry their time stamps", src)
    check_output(src, out, args.force)
    check_ranges(args)
    b = B.read_imu(src, args.topic, args.time_source, progress=progress)
    n = len(b.time_s)
    if not 0 < b.rate_hz <= MAX_RATE_HZ:
        raise InputError(f"topic {b.topic}: {b.time_source} gives {b.rate_hz:g} Hz, outside (0, {MAX_RATE_HZ:g}]: "
                         "not sample times", src, hint="try --time-source receive")
    # a field the sender did not fill (every message the same value, e.g. 0 from a gyro-only
    # driver) is no measurement: stored as NaN and left out of the axes rigctl allan analyses
    acc, gyr = b.specific_force, b.angular_rate
    unfilled = [axis_name(k, c) for k, d in (("accel", acc), ("gyro", gyr)) for c in range(3)
                if n >= 64 and np.ptp(d[:, c]) == 0.0]
    extra: list[str] = []
    axes = ""
    if unfilled:
        acc, gyr = acc.copy(), gyr.copy()
        for name in unfilled:
            (acc if SENSOR[name] == "accel" else gyr)[:, "xyz".index(name[-1])] = np.nan
        present = [k for k in REQUIRED if k not in unfilled]
        if not present:
            raise InputError(f"topic {b.topic}: every field of every message is constant: no measurement",
                             src, hint="check the topic (--topic) and the sender")
        axes = ",".join(present)
        sections = [{"label": "whole record", "start": 0, "end": n, "kind": "capture"}]
        origin = "the whole record (fields not filled: no static-interval detection)"
        extra.append(f"not filled in any message (the same value throughout), stored as NaN: "
                     f"{', '.join(unfilled)}; rigctl allan analyses the others ({axes})")
    else:
        sections, origin = find_sections(args, src, acc, gyr, b.rate_hz)
    gaps = (f"{b.gaps} gaps, {b.missing_samples} samples missing (/imu/counter jumps)" if b.gaps
            else "no gaps")
    meta = import_meta(args, src, b.rate_hz, origin, {
        "import_format": b.source_format, "import_topic": b.topic, "import_msgtype": b.msgtype,
        "import_frame_id": b.frame_id, "import_time_source": b.time_source,
        "import_columns_json": json.dumps({"acc": "linear_acceleration", "gyr": "angular_velocity",
                                           "time": b.time_source}),
        "import_units_json": json.dumps("m/s^2, rad/s (sensor_msgs/Imu, REP 103)"),
        "import_stamp_zero_ns": np.int64(b.stamp_zero_ns),
        "clock_zero_unix_s": b.stamp_zero_ns * 1e-9,
        "import_gaps": b.gaps, "import_missing_samples": b.missing_samples,
        "import_duplicates_dropped": b.duplicates_dropped,
        "import_receive_minus_stamp_s_json": json.dumps(b.receive_minus_stamp_s), "import_axes": axes})
    note = f"topic {b.topic}, {b.time_source}, rate {format_rate(b.rate_hz)}, {gaps}"
    if b.truncated:
        note += f"; {b.truncated}"
    span = _wall_clock_span(b.stamp_zero_ns, float(b.time_s[-1]) if n else 0.0)
    if span is not None:  # the capture's own start and end, not the import's
        meta["started_utc"] = span[0]
    write_recording(out, b.time_s, acc, gyr, np.full(n, np.nan), b.rate_hz,
                    sections, meta, counter=b.counter, note=note,
                    ended_utc=None if span is None else span[1])
    return Imported(out, n, b.rate_hz, sections,
                    [f"imported {n} samples from {args.file}", *B.describe(b), *extra], b.n_messages)


def is_bag(src: Path) -> bool:
    """A ROS bag, rosbag2 directory or MCAP file (by their first bytes), or a name that says so
    (a .bag/.mcap/.db3 whose content is none of them is then refused by the bag reader)."""
    return src.is_dir() or B.bag_kind(src) is not None or src.suffix.lower() in (".bag", ".mcap", ".db3")


def import_file(args: ImportOptions, progress: Progress | None = None) -> Imported:
    """Dispatch on the input: a bag (:func:`is_bag`), else CSV. ``progress(done, total)``:
    messages read from a bag."""
    src = Path(args.file)
    if not src.exists():
        raise InputError("input file not found", src)
    if is_bag(src):
        return import_bag(args, progress)
    return import_csv(args)


