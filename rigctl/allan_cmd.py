"""``rigctl allan RECORDING.h5``: Allan analysis of a recording's IMU channels.

Streams /imu/angular_rate (rad/s) and /imu/specific_force (m/s^2) in chunks (bounded
memory, all selected axes in one pass), computes the overlapping Allan deviation (fast mode by
default, ``--exact`` for the fully overlapping sums), Stable32-style noise identification, EDF
and 68 % / 95 % intervals, the joint IEEE 952 fit, prints a table per axis and stores
everything under /results/allan of the recording (attrs schema_version, created_utc, json;
curves as datasets with ``units``). ``--plot FILE`` writes a log-log plot (needs matplotlib).
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import os
import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np

from rigctl.analysis import noise_export, production
from rigctl.analysis.verdicts import format_verdicts
from rigctl.cli_options import add_production_options
from rigctl.errors import InputError
from rigctl.progress import WorkProgress
from rigctl.recording_reader import check_finite, open_recording, sample_rate
from rigctl.solvers import allan as A
from rigctl.solvers import allan_edf as E
from rigctl.solvers import allan_fit as F
from rigctl.solvers import allan_noise_id as NID
from rigctl.solvers.allan_crb import MAX_CAPTURE_S
from rigctl.spec import load_spec

AXES = {"gx": ("/imu/angular_rate", 0, "gyro"), "gy": ("/imu/angular_rate", 1, "gyro"),
        "gz": ("/imu/angular_rate", 2, "gyro"), "ax": ("/imu/specific_force", 0, "accel"),
        "ay": ("/imu/specific_force", 1, "accel"), "az": ("/imu/specific_force", 2, "accel")}
#: display unit of the deviation per sensor: (label, factor from SI)
DEV_UNITS = {"gyro": ("deg/h", 180.0 / math.pi * 3600.0), "accel": ("mg", 1000.0 / F.G0)}
MIN_SAMPLES = 64
CHUNK_ROWS = 1 << 20
HEAD_POINTS = 1 << 22  # full-resolution phase kept for noise ID at short taus
DEC_POINTS = 1 << 21  # the phase is also kept decimated to at most ~this many points
SCHEMA_VERSION = 1


#: invalid input (exit code 2): the one error type of rigctl.errors
UsageError = InputError


class _AxisStream:
    """Accumulates one axis: Allan sums (streamed), plus for the noise identification a
    full-resolution phase head and the whole phase decimated by ``dec`` (bounded memory)."""

    def __init__(self, tau0: float, ms: np.ndarray, mode: str, n_rate: int):
        self.acc = A.OadevAccumulator(tau0, ms, mode)
        self.dec = 1
        while (n_rate + 1) // self.dec > DEC_POINTS:
            self.dec *= 2
        self.head: list[np.ndarray] = []
        self.n_head = 0
        self.decs: list[np.ndarray] = [np.zeros(1)]  # x[0] = 0
        self.part = np.empty(0)  # rate samples of the unfinished decimation block
        self.tau0 = tau0
        self.x_dec = 0.0  # phase at the last decimated point
        self.x_head = 0.0
        self.n_rate = 0

    def add(self, y: np.ndarray) -> None:
        acc = self.acc
        acc.add_rate(y)
        c = acc.offset
        if self.n_head < HEAD_POINTS:  # full-resolution phase of the first samples
            part = y[: HEAD_POINTS - self.n_head] - c
            x = np.cumsum(part) * self.tau0 + self.x_head
            if self.n_head == 0:
                x = np.concatenate(([0.0], x))
            self.head.append(x)
            self.n_head += x.size
            self.x_head = float(x[-1])
        if self.dec == 1:
            self.decs.append(np.cumsum(y - c) * self.tau0 + self.x_dec)
            self.x_dec = float(self.decs[-1][-1])
        else:  # block sums of dec samples, then a short running sum
            z = np.concatenate((self.part, y)) if self.part.size else y
            nb = z.size // self.dec
            if nb:
                sums = z[: nb * self.dec].reshape(nb, self.dec).sum(axis=1) - self.dec * c
                xs = np.cumsum(sums) * self.tau0 + self.x_dec
                self.decs.append(xs)
                self.x_dec = float(xs[-1])
            self.part = z[nb * self.dec:].copy()
        self.n_rate += y.size

    def noise_id(self, m: int, n: int) -> int:
        """Stable32's noise ID at factor m (no hold); ``n``: the full record's term count."""
        if not hasattr(self, "_head"):
            self._head = np.concatenate(self.head)
            self._dec = np.concatenate(self.decs)
            self.head, self.decs = [], []
        if m % self.dec == 0:
            return NID.noise_id(self._dec, m // self.dec, "oadev", n)
        return NID.noise_id(self._head, m, "oadev", n)


def analyse_axis(stream: _AxisStream, sensor: str) -> dict[str, Any]:
    """Deviation curve, confidence and fits of one streamed axis (SI + field units)."""
    res = stream.acc.result()
    raw = [stream.noise_id(int(m), NID.n_terms("oadev", res.n_phase, int(m))) for m in res.m]
    held = NID.apply_hold(res.m, raw, res.n_phase, "oadev")
    alphas = np.array([NID.clamp_alpha(int(a), "oadev") for a in held])
    edfs = np.array([E.edf("oadev", int(a), int(m), res.n_phase) for a, m in zip(alphas, res.m)])
    lo68, hi68 = E.chi2_interval(res.dev, edfs, E.ONE_SIGMA)
    lo95, hi95 = E.chi2_interval(res.dev, edfs, 0.95)
    fit = F.fit_terms(res.tau_s, res.dev, edfs, sensor, tau0=res.tau0_s, n_phase=res.n_phase)
    pw = F.piecewise_readoffs(res.tau_s, res.dev, sensor)
    unit, fac = DEV_UNITS[sensor]
    si = "rad/s" if sensor == "gyro" else "m/s^2"
    return {"sensor": sensor, "n_samples": int(res.n_phase - 1), "mode": stream.acc.mode,
            "tau_s": res.tau_s, "m": res.m, "stride": res.stride, "n_terms": res.n_terms,
            f"adev_{si}": res.dev, f"adev_{unit}": res.dev * fac,
            f"lo68_{unit}": lo68 * fac, f"hi68_{unit}": hi68 * fac,
            f"lo95_{unit}": lo95 * fac, f"hi95_{unit}": hi95 * fac,
            "alpha": alphas, "edf": edfs, "fit": fit, "piecewise": pw,
            "_si": si, "_unit": unit}


def _open_checked(path: str, axes: list[str]):
    """The recording, checked (rigctl.recording_reader) for the datasets of ``axes``."""
    return open_recording(path, ["imu/time", *sorted({AXES[a][0].lstrip("/") for a in axes})])


def _sample_rate(f, path: str) -> float:
    return sample_rate(f)


def compute(path: str, axes: list[str], taus: A.TauSpec = 95, exact: bool = False,
            sample_range: tuple[int, int] | None = None,
            progress_stream: Any = None) -> dict[str, Any]:
    """Stream the recording and analyse ``axes`` (IMU samples ``sample_range`` = [first,
    last) if given, else all); raises UsageError on invalid input. With ``progress_stream``
    (a console), progress is shown there (a bar on a terminal, a line per 10 s otherwise)."""
    with _open_checked(path, axes) as f:
        fs = _sample_rate(f, path)
        dsets = {name: f[name] for name in {AXES[a][0] for a in axes}}
        n_all = min(d.shape[0] for d in dsets.values())
        s0, s1 = (0, n_all) if sample_range is None else (
            max(0, int(sample_range[0])), min(n_all, int(sample_range[1])))
        n = max(0, s1 - s0)
        if n < MIN_SAMPLES:
            raise UsageError(f"{path}: only {n} IMU samples; need at least {MIN_SAMPLES} "
                             "for an Allan analysis (record longer)")
        gaps = _counter_gaps(f, s0, s1)
        tau0 = 1.0 / fs
        ms = A.tau_factors(n + 1, taus, "oadev")
        mode = "exact" if exact else "fast"
        if mode == "fast" and not isinstance(taus, (list, tuple)):
            ms = A.snap_fast(ms)
            ms = ms[ms <= A.max_factor(n + 1, "oadev")]
        streams = {a: _AxisStream(tau0, ms, mode, n) for a in axes}
        shown = WorkProgress(f"allan {os.path.basename(path)}, {len(axes)} axes", n,
                             stream=progress_stream, enabled=progress_stream is not None)
        for a0 in range(s0, s1, CHUNK_ROWS):
            a1 = min(s1, a0 + CHUNK_ROWS)
            blocks = {name: np.asarray(d[a0:a1], dtype=np.float64) for name, d in dsets.items()}
            for name, b in blocks.items():
                check_finite(path, name, b, a0)
            for a in axes:
                name, col, _ = AXES[a]
                streams[a].add(np.ascontiguousarray(blocks[name][:, col]))
            del blocks
            shown.update(a1 - s0)
        shown.finish()
    out = {"file": os.path.basename(path), "sample_rate_hz": fs, "n_samples": int(n),
           "first_sample": int(s0), "dropped_samples": int(gaps), "axes": {}}
    for a in axes:
        out["axes"][a] = analyse_axis(streams[a], AXES[a][2])
        streams[a] = None  # free the per-axis buffers
    return out


def _counter_gaps(f: Any, s0: int, s1: int) -> int:
    """Samples missing according to /imu/counter in [s0, s1) (0 without a counter)."""
    if "/imu/counter" not in f:
        return 0
    c = f["/imu/counter"]
    if c.shape[0] < s1 or s1 - s0 < 2:
        return 0
    first, last = int(c[s0]), int(c[s1 - 1])
    return max(0, (last - first + 1) - (s1 - s0))


def _capture_range(f: Any) -> tuple[int, int, str] | None:
    """Sample range of the longest ``capture`` segment (complete preferred), or None."""
    seg = f.get("/segments")
    if seg is None or any(k not in seg for k in ("kind", "first_sample", "last_sample")):
        return None
    kinds = [bytes(k).rstrip(b"\0") for k in seg["kind"][:]]
    first, last = seg["first_sample"][:], seg["last_sample"][:]
    status = ([bytes(s).rstrip(b"\0") for s in seg["status"][:]] if "status" in seg
              else [b"complete"] * len(kinds))
    labels = ([bytes(s).rstrip(b"\0").decode(errors="replace") for s in seg["label"][:]]
              if "label" in seg else [""] * len(kinds))
    cand = [(st == b"complete", int(b) - int(a), int(a), int(b), lab)
            for k, a, b, st, lab in zip(kinds, first, last, status, labels) if k == b"capture"]
    if not cand:
        return None
    best = max(cand)
    return best[2], best[3], best[4]


def table_motion(f: Any, s0: int, s1: int) -> tuple[float, float]:
    """Largest |table rate| (deg/s) and largest angle excursion (deg) over the IMU samples
    [s0, s1), from /table; (0, 0) when the recording has no table data."""
    if any(n not in f for n in ("/table/rate", "/table/time", "/table/angle", "/imu/time")) or s1 <= s0:
        return 0.0, 0.0
    t = f["/imu/time"]
    t0, t1 = float(t[s0]), float(t[s1 - 1])
    tt = f["/table/time"][:]
    sel = (tt >= t0) & (tt <= t1)
    if not sel.any():
        return 0.0, 0.0
    rate = np.degrees(np.abs(f["/table/rate"][:][sel]))
    ang = np.degrees(f["/table/angle"][:][sel])
    rate, ang = rate[np.isfinite(rate)], ang[np.isfinite(ang).all(axis=1)]  # unreadable polls: no motion known
    return (float(rate.max()) if rate.size else 0.0,
            float((ang.max(axis=0) - ang.min(axis=0)).max()) if len(ang) else 0.0)


#: above these the analysed range is not a static capture (deg/s, deg)
STATIC_RATE_DPS, STATIC_ANGLE_DEG = 0.01, 0.01


def choose_range(path: str, axes: list[str], whole: bool = False
                 ) -> tuple[tuple[int, int] | None, str, str]:
    """The IMU sample range to analyse -- the longest capture segment unless ``whole`` -- its
    description, and a warning ('' if none) when the table moved in it. Raises UsageError for
    a file that is not a recording with ``axes``."""
    with _open_checked(path, axes) as f:
        rng = None if whole else _capture_range(f)
        s0, s1 = (0, int(f["/imu/time"].shape[0]) if "/imu/time" in f else 0) if rng is None else rng[:2]
        rate, span = table_motion(f, s0, s1)
    where = "whole recording" if rng is None else f"capture segment '{rng[2]}'"
    warn = ""
    if rate > STATIC_RATE_DPS or span > STATIC_ANGLE_DEG:
        warn = (f"the table moved during the analysed range ({where}: up to {rate:.3g} deg/s, "
                f"{span:.3g} deg): an Allan analysis needs a static capture, so these terms are "
                "not the sensor's noise; record one with procedures/allan-overnight.yaml")
    return (None if rng is None else rng[:2]), where, warn


def solve_recording(path: Path, log: Callable[[str, str], Any]) -> None:
    """Solver hook for a procedure's ``solve: [allan]`` step: default analysis (fast mode,
    95 log-spaced taus, all six axes present) of the longest capture segment (whole record
    if it has none), stored in /results/allan; a short summary goes to ``log("info", ...)``.
    """
    import h5py

    path = str(path)
    with h5py.File(path, "r") as f:
        axes = [a for a in AXES if AXES[a][0] in f]
    if not axes:
        log("warning", f"allan: {path} has no /imu/angular_rate or /imu/specific_force")
        return
    rng, where, warn = choose_range(path, axes)
    if warn:
        log("warning", f"allan: {warn}")
    try:
        result = compute(path, axes, 95, False, rng)
    except UsageError as exc:
        log("warning", f"allan: not run: {exc}")
        return
    result["segment"] = where
    store(path, result)
    log("info", "allan: " + production.to_database(path, "allan", result, None))
    n, fs = result["n_samples"], result["sample_rate_hz"]
    log("info", f"allan: {where}, {n} samples at {fs:g} Hz ({n / fs / 3600:.2f} h); "
                f"results in {path}:/results/allan")
    if result["dropped_samples"]:
        log("warning", f"allan: {result['dropped_samples']} samples missing (counter gaps) "
                       "in the analysed range; the deviations assume uniform sampling")
    for a, r in result["axes"].items():
        log("info", f"allan {a}: " + summary_line(r))


def summary_line(r: dict[str, Any]) -> str:
    """One line per axis: fitted N, B, K with 95 % intervals or upper bounds."""
    parts = []
    for t in ("N", "B", "K"):
        e = r["fit"]["terms"][t]
        unit = F.FIELD_UNITS[r["sensor"]][t][0]
        if e["supported"]:
            lo, hi = e[f"ci95_{unit}"]
            parts.append(f"{t} {e[f'value_{unit}']:.4g} {unit} [{lo:.4g}, {hi:.4g}]")
        else:
            parts.append(f"{t} < {e[f'upper95_{unit}']:.4g} {unit}")
    return "; ".join(parts)


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items() if not k.startswith("_")}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating,)):
        return float(obj)
    return obj


def store(path: str, result: dict[str, Any]) -> None:
    """Write /results/allan (replacing an earlier one): JSON summary + curve datasets."""
    import h5py

    with h5py.File(path, "r+") as f:
        grp = f.require_group("results")
        if "allan" in grp:
            del grp["allan"]
        g = grp.create_group("allan")
        summary = {"file": result["file"], "sample_rate_hz": result["sample_rate_hz"],
                   "n_samples": result["n_samples"],
                   "first_sample": result.get("first_sample", 0),
                   "dropped_samples": result.get("dropped_samples", 0),
                   "segment": result.get("segment", "whole recording"),
                   **({"verdicts": result["verdicts"]} if result.get("verdicts") else {}),
                   "axes": {a: {"sensor": r["sensor"], "mode": r["mode"],
                                "fit": _jsonable(r["fit"]),
                                "piecewise": _jsonable(r["piecewise"])}
                            for a, r in result["axes"].items()}}
        g.attrs["schema_version"] = SCHEMA_VERSION
        g.attrs["created_utc"] = _dt.datetime.now(_dt.timezone.utc).isoformat()
        g.attrs["json"] = json.dumps(summary)
        for a, r in result["axes"].items():
            ga = g.create_group(a)
            unit = r["_unit"]
            for key, units in (("tau_s", "s"), ("m", "1"), ("stride", "1"), ("n_terms", "1"),
                               (f"adev_{r['_si']}", r["_si"]), (f"adev_{unit}", unit),
                               (f"lo68_{unit}", unit), (f"hi68_{unit}", unit),
                               (f"lo95_{unit}", unit), (f"hi95_{unit}", unit),
                               ("alpha", "1"), ("edf", "1")):
                name = key.replace("/", "_per_")
                ds = ga.create_dataset(name, data=np.asarray(r[key]))
                ds.attrs["units"] = units


def capture_text(h: float) -> str:
    """A capture length in hours for people: '47 h', '12 days'; inf (beyond what
    allan_crb.duration_for considers) 'more than 417 days'."""
    if not math.isfinite(h):
        return f"more than {MAX_CAPTURE_S / 86400:.0f} days"
    return f"{h:.0f} h" if h < 72 else f"{h / 24:.0f} days"


def format_table(axis: str, r: dict[str, Any]) -> str:
    """Human-readable table of one axis plus its fitted terms."""
    unit = r["_unit"]
    lines = [f"== {axis} ({r['sensor']}, {r['n_samples']} samples, {r['mode']} mode)",
             f"{'tau_s':>12} {'adev_' + unit:>14} {'lo68':>12} {'hi68':>12} "
             f"{'alpha':>5} {'edf':>10}"]
    for i in range(len(r["tau_s"])):
        lines.append(f"{r['tau_s'][i]:12.5g} {r['adev_' + unit][i]:14.6g} "
                     f"{r['lo68_' + unit][i]:12.6g} {r['hi68_' + unit][i]:12.6g} "
                     f"{int(r['alpha'][i]):5d} {r['edf'][i]:10.4g}")
    lines.append("fitted terms (joint EDF-weighted fit; 95 % intervals):")
    for t, e in r["fit"]["terms"].items():
        unit_f = F.FIELD_UNITS[r["sensor"]][t][0]
        need = e.get("capture_h_for_25pct")
        if e["supported"]:
            lo, hi = e[f"ci95_{unit_f}"]
            more = ("" if need is None else f" (this capture: +-{100 * e['crb_rel_sd']:.0f} % at best "
                    f"(Cramer-Rao); +-25 % needs about {capture_text(need)})")
            lines.append(f"  {e['name']:>26}: {e[f'value_{unit_f}']:.5g} {unit_f} "
                         f"[{lo:.5g}, {hi:.5g}]{more}")
        else:
            more = "" if need is None else f"; +-25 % would need at least {capture_text(need)} of capture"
            lines.append(f"  {e['name']:>26}: < {e[f'upper95_{unit_f}']:.5g} {unit_f} "
                         f"(95 % upper bound; not supported by the data{more})")
    pw = r["piecewise"]["terms"]
    parts = []
    for t in ("N", "B", "K"):
        unit_f = F.FIELD_UNITS[r["sensor"]][t][0]
        v = pw[t][f"value_{unit_f}"]
        parts.append(f"{t}={'n/a' if v is None else format(v, '.5g')} {unit_f}")
    lines.append("piecewise read-offs (for comparison): " + ", ".join(parts))
    return "\n".join(lines)


def plot(result: dict[str, Any], out_path: str) -> None:
    """Log-log plot: deviation with 68 % bars, fitted total and each term's line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    axes = list(result["axes"].items())
    fig, subs = plt.subplots(len(axes), 1, figsize=(7, 3.2 * len(axes)), squeeze=False)
    for ax, (name, r) in zip(subs[:, 0], axes):
        unit, fac = DEV_UNITS[r["sensor"]]
        tau = np.asarray(r["tau_s"])
        dev = np.asarray(r[f"adev_{unit}"])
        err = [dev - r[f"lo68_{unit}"], r[f"hi68_{unit}"] - dev]
        ax.errorbar(tau, dev, yerr=err, fmt=".", ms=3, lw=0.8, label="overlapping ADEV (68 %)")
        tt = np.logspace(np.log10(tau.min()), np.log10(tau.max()), 200)
        cols = F.design_matrix(tt)
        p = r["fit"]["coeff_sq_si"]
        total = np.zeros_like(tt)
        for j, t in enumerate(F.TERMS):
            part = cols[:, j] * p.get(t, 0.0)
            total += part
            if p.get(t, 0.0) > 0:
                ax.loglog(tt, np.sqrt(part) * fac, "--", lw=0.8, label=f"{t} term")
        ax.loglog(tt, np.sqrt(total) * fac, "k-", lw=1.2, label="fitted total")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(name)
        ax.set_xlabel("tau [s]")
        ax.set_ylabel(f"Allan deviation [{unit}]")
        ax.grid(True, which="both", lw=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out_path, dpi=120)
    plt.close(fig)


def _parse_taus(text: str) -> A.TauSpec:
    if text in ("octave", "decade", "all"):
        return text
    try:
        n = int(text)
    except ValueError:
        raise UsageError(f"--taus {text!r}: use octave, decade, all or a number") from None
    if n < 2:
        raise UsageError("--taus N needs N >= 2")
    return n


def _parse_axes(text: str) -> list[str]:
    axes = list(dict.fromkeys(a.strip() for a in text.split(",") if a.strip()))
    bad = [a for a in axes if a not in AXES]
    if not axes or bad:
        raise UsageError(f"--axes {text!r}: choose from {','.join(AXES)}")
    return axes


def run(args: argparse.Namespace) -> int:
    """Entry point of ``rigctl allan``: 0 ok; errors are raised (rigctl.errors, mapped to exit
    codes by rigctl.cli.main)."""
    axes = _parse_axes(args.axes)
    taus = _parse_taus(str(args.taus))
    if args.plot:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            raise UsageError("--plot needs matplotlib: pip install 'rigctl[report]'") from None
    if args.kalibr and set(axes) != set(AXES):
        raise UsageError("--kalibr needs all six axes (--axes gx,gy,gz,ax,ay,az)")
    if not args.kalibr_inflate > 0:
        raise UsageError(f"--kalibr-inflate {args.kalibr_inflate:g}: give a factor > 0 (1: none)")
    rng, where, warn = choose_range(args.recording, axes, args.whole)
    print(f"analysing the {where} of {args.recording}", flush=True)
    if warn:
        print(f"warning: {warn}", file=sys.stderr, flush=True)
    spec = load_spec(args.spec, args.decision_rule) if args.spec else None
    result = compute(args.recording, axes, taus, args.exact, rng, progress_stream=sys.stderr)
    result["segment"] = where
    for a, r in result["axes"].items():
        print(format_table(a, r))
    result["verdicts"] = production.verdicts_for(spec, "allan", result)
    if result["verdicts"]:
        print(format_verdicts(result["verdicts"]))
    store(args.recording, result)
    print(f"results written to {args.recording}:/results/allan")
    print(production.to_database(args.recording, "allan", result, args.db))
    if args.plot:
        plot(result, args.plot)
        print(f"plot written to {args.plot}")
    export(args, result)
    return 0


def export(args: argparse.Namespace, result: dict[str, Any]) -> None:
    """--kalibr, --json, --csv (rigctl.analysis.noise_export)."""
    kalibr = noise_export.kalibr_values(result, args.kalibr_inflate) if args.kalibr else None
    if args.kalibr:
        import h5py

        with h5py.File(args.recording, "r") as f:
            topic = args.kalibr_topic or noise_export.imu_topic(f["meta"].attrs if "meta" in f else {})
        Path(args.kalibr).write_text(noise_export.kalibr_yaml(result, topic, args.kalibr_inflate))
        print(f"Kalibr imu.yaml written to {args.kalibr}"
              + ("" if args.kalibr_inflate == 1 else f" (values x{args.kalibr_inflate:g})"))
    if args.json:
        Path(args.json).write_text(noise_export.allan_json(result, kalibr))
        print(f"JSON written to {args.json}")
    if args.csv:
        Path(args.csv).write_text(noise_export.deviation_csv(result))
        print(f"deviation table written to {args.csv}")


def register(subparsers: Any) -> None:
    """Add the ``allan`` subcommand (sets ``func=run``)."""
    p = subparsers.add_parser("allan", help="Allan analysis of a recording's IMU channels",
                              description=__doc__.splitlines()[0])
    p.add_argument("recording", help="rigctl HDF5 recording (results are written into it)")
    p.add_argument("--axes", default="gx,gy,gz,ax,ay,az",
                   help="comma-separated axes from gx,gy,gz,ax,ay,az (default: all)")
    p.add_argument("--plot", metavar="FILE", help="write a log-log plot (needs matplotlib)")
    p.add_argument("--taus", default="95",
                   help="octave, decade, all, or N log-spaced taus (default 95)")
    p.add_argument("--whole", action="store_true",
                   help="analyse the whole recording (default: its longest capture segment, if any)")
    p.add_argument("--exact", action="store_true",
                   help="fully overlapping sums for every tau (slower; default: fast mode)")
    p.add_argument("--kalibr", metavar="FILE", help="write Kalibr's imu.yaml (noise densities and random "
                   "walks, SI; the largest axis per sensor; docs/allan.md)")
    p.add_argument("--kalibr-inflate", type=float, default=1.0, metavar="X",
                   help="multiply the Kalibr values by X (default 1: as fitted); stated in the file")
    p.add_argument("--kalibr-topic", metavar="TOPIC",
                   help="rostopic in imu.yaml (default: the bag topic of an imported recording, else /imu0)")
    p.add_argument("--json", metavar="FILE", help="write the whole Allan result as JSON")
    p.add_argument("--csv", metavar="FILE", help="write the deviation table (tau, sigma, bands, terms; SI) as CSV")
    add_production_options(p)
    p.set_defaults(func=run)
