"""`rigctl sync RECORDING.h5`: tap-hammer time synchronisation of a recording.

Reads /imu/counter, /imu/specific_force (+ /imu attrs sample_rate_hz) and /pulses/* from a
rigctl recording, detects taps, matches them to the pulses, fits the IMU clock and writes
/results/sync (attrs schema_version, created_utc, json; dataset reference_time with a
reference time for every IMU sample, and the matched pairs). See docs/sync.md.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rigctl.errors import InputError, RunFailure
from rigctl.recorder import write_results as store_results
from rigctl.recording_reader import check_finite, open_recording, sample_rate
from rigctl.solvers import clock_model, tap_detect, tap_match

AXES = {"x": 0, "y": 1, "z": 2}
GPS_WEEK_S = 604800.0


@dataclass
class SyncOptions:
    """Options of the synchronisation pipeline (times in s)."""

    response: str = "auto"  # auto | none | learn | second-order
    natural_freq_hz: float = 30.0
    damping: float = 0.7
    wander: str | None = None
    tolerance_s: float = 0.05
    outlier_k: float = 5.0
    outlier_floor_s: float = 1e-3
    group_gap_s: float = 30.0
    saturation_m_s2: float | None = None  # None: auto (repeated extreme values)


@dataclass
class SyncResult:
    """Everything the pipeline found (pure data; no I/O)."""

    detections: tap_detect.Detections
    tap_time_s: np.ndarray  # IMU timescale, after half-sample correction or onset fit
    timing: str  # "subsample" | "half_sample"
    response: tap_detect.SecondOrderResponse | None
    match: tap_match.MatchResult
    clock: clock_model.ClockFit
    virtual: tap_match.VirtualTaps
    summary: dict[str, Any]


def synchronise(counter: np.ndarray, accel: np.ndarray, rate_hz: float,
                pulse_time_s: np.ndarray, opts: SyncOptions | None = None) -> SyncResult:
    """Run detection, matching and the clock fit on arrays (``accel``: tap axis, m/s^2)."""
    opts = opts or SyncOptions()
    c = np.asarray(counter).astype(np.float64)
    a = np.asarray(accel, dtype=float)
    period = 1.0 / rate_hz
    t_imu = c * period
    det = tap_detect.first_difference_detect(
        a, saturation_level=opts.saturation_m_s2,
        min_separation=max(3, int(round(0.3 * rate_hz))))  # one event per 0.3 s
    if det.index.size < 3:
        raise ValueError(f"only {det.index.size} taps detected; need at least 3")
    sat = tap_detect.saturation_mask(a, opts.saturation_m_s2)
    post = max(8, int(round(0.2 * rate_hz)))  # fit window: 0.2 s after the tap
    response = None
    timing = "half_sample"
    tap_t = tap_match.half_sample_correction(t_imu[det.index], period)
    if opts.response in ("auto", "learn", "second-order"):
        try:
            if opts.response == "second-order":
                response = tap_detect.SecondOrderResponse(opts.natural_freq_hz, opts.damping)
            else:
                response = tap_detect.learn_response(t_imu, a, det.index, saturated=sat,
                                                     post=post)
            on = tap_detect.fit_onsets(t_imu, a, det.index, response, post=post,
                                       saturated=sat)
        except (ValueError, np.linalg.LinAlgError):
            if opts.response != "auto":
                raise
            on = None
        noise = det.sigma_diff / np.sqrt(2.0)
        fits = (on is not None and response is not None
                and np.nanmedian(on.rms_residual) < 3.0 * noise
                and response.natural_freq_hz < 0.5 * rate_hz)
        if on is not None and (fits or opts.response != "auto"):
            ok = np.isfinite(on.t0)
            tap_t = np.where(ok, on.t0, tap_t)
            timing = "subsample"
        else:
            response = None
    m = tap_match.match_taps(tap_t, pulse_time_s, tolerance_s=opts.tolerance_s,
                             outlier_k=opts.outlier_k, outlier_floor_s=opts.outlier_floor_s)
    if m.inlier.sum() < 3:
        raise ValueError(f"only {int(m.inlier.sum())} taps matched pulses; need at least 3")
    ti, pj = m.tap_index[m.inlier], m.pulse_index[m.inlier]
    fit = clock_model.fit_clock(tap_t[ti] * rate_hz, pulse_time_s[pj], rate_hz,
                                wander=opts.wander, outlier_k=opts.outlier_k,
                                outlier_floor_s=opts.outlier_floor_s, gap_counter=counter)
    vt = tap_match.virtual_taps(tap_t[ti], pulse_time_s[pj], opts.group_gap_s)
    summary = _summary(det, timing, response, m, fit, vt, pulse_time_s.size, rate_hz, counter)
    return SyncResult(det, tap_t, timing, response, m, fit, vt, summary)


def _summary(det: tap_detect.Detections, timing: str,
             response: tap_detect.SecondOrderResponse | None, m: tap_match.MatchResult,
             fit: clock_model.ClockFit, vt: tap_match.VirtualTaps, n_pulses: int,
             rate_hz: float, counter: np.ndarray) -> dict[str, Any]:
    t95 = fit.t95
    out: dict[str, Any] = {
        "rate_hz": rate_hz, "timing": timing,
        "response": None if response is None else {
            "natural_freq_hz": response.natural_freq_hz, "damping": response.damping},
        "offset_s": fit.offset_s, "offset_sigma_s": fit.offset_sigma_s,
        "offset_ci95_s": t95 * fit.offset_sigma_s,
        "drift_ppm": fit.drift_ppm, "drift_sigma_ppm": fit.drift_sigma_ppm,
        "drift_ci95_ppm": t95 * fit.drift_sigma_ppm,
        "n_taps_detected": int(det.index.size), "n_pulses": int(n_pulses),
        "n_matched": int(m.tap_index.size), "n_inliers": int(fit.inlier.sum()),
        "n_outliers": int((~m.inlier).sum() + (~fit.inlier).sum()),
        "n_saturated_taps": int(det.saturated.sum()),
        "n_taps_without_pulse": int(m.unmatched_taps.size),
        "n_pulses_without_tap": int(m.unmatched_pulses.size),
        "residual_std_ms": fit.residual_std_s * 1e3,
        "outlier_limit_ms": fit.outlier_limit_s * 1e3,
        "wander": fit.wander,
        "counter_gaps": [{"row": r, "first_missing_counter": c, "n_samples": n}
                         for r, c, n in fit.counter_gaps],
        "residual_steps": [{"after_counter": b, "n_samples": k, "bracket_counter": list(br)}
                           for (b, k), br in zip(fit.steps, fit.step_brackets)],
        "virtual_taps": [{"tap_time_s": float(a), "pulse_time_s": float(b),
                          "offset_ms": float(c) * 1e3, "offset_sem_ms": float(d) * 1e3,
                          "count": int(e)} for a, b, c, d, e in
                         zip(vt.tap_time_s, vt.pulse_time_s, vt.offset_s, vt.offset_sem_s,
                             vt.count)],
    }
    if vt.count.size >= 2:
        c = np.asarray(counter, dtype=np.int64)
        c0, c1 = vt.tap_time_s[0] * rate_hz, vt.tap_time_s[-1] * rate_hz
        lost = sum(n for _, first, n in fit.counter_gaps if c0 < first < c1)
        lost += sum(k for b, k in fit.steps if c0 < b < c1)
        counted = c1 - c0 + sum(k for b, k in fit.steps if c0 < b < c1)
        chk = clock_model.sample_count_check(0.0, counted, vt.pulse_time_s[0],
                                             vt.pulse_time_s[-1], rate_hz, lost)
        chk["rows_in_recording"] = int(np.sum((c >= c0) & (c < c1)))
        out["sample_count_check"] = chk
    return out


def register(subparsers: Any) -> None:
    """Add the ``sync`` subcommand (``func=run``)."""
    p = subparsers.add_parser("sync", help="tap-hammer time synchronisation of a recording",
                              description=__doc__)
    p.add_argument("recording", type=Path, help="recording .h5 (opened r+; /results/sync written)")
    p.add_argument("--axis", choices=sorted(AXES), default="z", help="tap axis (default z)")
    p.add_argument("--plot-dir", type=Path, default=None, help="write PNG plots here")
    p.add_argument("--response", choices=["auto", "none", "learn", "second-order"],
                   default="auto", help="sensor response for sub-sample timing (default auto)")
    p.add_argument("--natural-freq-hz", type=float, default=30.0)
    p.add_argument("--damping", type=float, default=0.7)
    p.add_argument("--wander", choices=["none", "quadratic"], default="none")
    p.add_argument("--timescale", choices=["run", "gps"], default="run",
                   help="pulse times from /pulses/time (run) or gps_week/gps_seconds (gps)")
    p.add_argument("--tolerance-s", type=float, default=0.05, help="matching gate (s)")
    p.add_argument("--range-m-s2", type=float, default=None,
                   help="accelerometer saturation level (default: repeated extreme values)")
    p.set_defaults(func=run)


def _read(path: Path, axis: int, timescale: str) -> tuple[Any, ...]:
    """(counter, specific force of ``axis``, sample rate Hz, pulse times s); InputError naming
    the file for anything a synchronisation cannot use (rigctl.recording_reader checks the rest)."""
    with open_recording(path, ["imu/counter", "imu/specific_force", "pulses/time"]) as f:
        rate = sample_rate(f)
        counter = f["imu/counter"][()]
        sf = f["imu/specific_force"][()]
        if timescale == "gps":
            if "pulses/gps_week" not in f or "pulses/gps_seconds" not in f:
                raise InputError("no /pulses/gps_week or gps_seconds", path, hint="use --timescale run")
            week = f["pulses/gps_week"][()].astype(float)
            if np.any(week < 0):
                raise InputError("some pulses have no GPS week (-1)", path, hint="use --timescale run")
            pulses = week * GPS_WEEK_S + f["pulses/gps_seconds"][()]
        else:
            pulses = f["pulses/time"][()]
    check_finite(path, "imu/specific_force", sf)
    check_finite(path, "pulses/time" if timescale == "run" else "pulses/gps_seconds", pulses)
    if sf.shape[0] != counter.shape[0]:
        raise InputError("/imu/specific_force and /imu/counter differ in length", path)
    if counter.size < 10 or np.any(np.diff(counter.astype(np.int64)) <= 0):
        raise InputError("/imu/counter must be strictly increasing with at least 10 samples", path)
    if pulses.size < 3:
        raise InputError(f"{pulses.size} pulses recorded", path,
                         hint="tap at least 3 times with the pulse input on")
    return counter, sf[:, axis], float(rate), np.asarray(pulses, dtype=float)


def _positive(name: str, value: float | None, maximum: float = 1e9) -> None:
    """InputError unless ``value`` (an option) is None or finite in (0, ``maximum``]."""
    if value is not None and not (np.isfinite(value) and 0.0 < value <= maximum):
        raise InputError(f"{name} {value:g}: must be a finite number in (0, {maximum:g}]")


def write_results(path: Path, res: SyncResult, counter: np.ndarray, pulses: np.ndarray,
                  args_dict: dict[str, Any]) -> None:
    """Write /results/sync (replacing an earlier one)."""
    ref = res.clock.time_of_counter(np.asarray(counter).astype(np.float64))
    m = res.match
    store_results(path, "sync", {**res.summary, "options": args_dict}, {
        "reference_time": (ref, "s"),
        "tap_time_imu": (res.tap_time_s[m.tap_index], "s"),
        "tap_row": (res.detections.index[m.tap_index].astype(np.int64), "1"),
        "pulse_index": (m.pulse_index.astype(np.int64), "1"),
        "pulse_time": (pulses[m.pulse_index], "s"),
        "local_residual": (m.local_residual_s, "s"),
        "inlier": (m.inlier.astype(np.uint8), "1"),
    })


def plot(res: SyncResult, pulses: np.ndarray, plot_dir: Path) -> list[Path]:
    """Matching-error histogram (as the paper's figure 7) and residual against time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plot_dir.mkdir(parents=True, exist_ok=True)
    m = res.match
    tap_ref = res.clock.time_of_counter(res.tap_time_s[m.tap_index] * res.summary["rate_hz"])
    err_ms = (pulses[m.pulse_index] - tap_ref) * 1e3
    out = []
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.hist(err_ms[m.inlier], bins=30, color="tab:blue", label="inliers")
    if (~m.inlier).any():
        ax.hist(err_ms[~m.inlier], bins=30, color="tab:red", label="outliers")
    ax.set_xlabel("matching error: pulse - tap [ms]")
    ax.set_ylabel("count")
    ax.set_title(f"tap matching error ({res.timing}), std {res.summary['residual_std_ms']:.3f} ms")
    ax.legend()
    out.append(plot_dir / "sync_matching_error_hist.png")
    fig.savefig(out[-1], dpi=100)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(pulses[m.pulse_index][m.inlier], err_ms[m.inlier], "o", ms=3, label="inliers")
    ax.plot(pulses[m.pulse_index][~m.inlier], err_ms[~m.inlier], "x", color="tab:red",
            label="outliers")
    ax.set_xlabel("reference time [s]")
    ax.set_ylabel("residual [ms]")
    ax.legend()
    out.append(plot_dir / "sync_residual_vs_time.png")
    fig.savefig(out[-1], dpi=100)
    plt.close(fig)
    return out


def run(args: argparse.Namespace) -> int:
    """CLI entry: 0 ok; errors are raised (rigctl.errors: 2 invalid input, 1 failure)."""
    path: Path = args.recording
    _positive("--natural-freq-hz", args.natural_freq_hz, 1e5)
    _positive("--damping", args.damping, 100.0)
    _positive("--tolerance-s", args.tolerance_s, 3600.0)
    _positive("--range-m-s2", args.range_m_s2, 1e6)
    counter, accel, rate, pulses = _read(path, AXES[args.axis], args.timescale)
    opts = SyncOptions(response=args.response, natural_freq_hz=args.natural_freq_hz,
                       damping=args.damping,
                       wander=None if args.wander == "none" else args.wander,
                       tolerance_s=args.tolerance_s, saturation_m_s2=args.range_m_s2)
    try:
        res = synchronise(counter, accel, rate, pulses, opts)
    except ValueError as exc:
        raise RunFailure(f"{path}: {exc}") from None
    s = res.summary
    print(f"sync {path}: timing {s['timing']}, axis {args.axis}")
    print(f"  offset      {s['offset_s']:.6f} s  (1-sigma {s['offset_sigma_s'] * 1e3:.3f} ms, "
          f"95% +-{s['offset_ci95_s'] * 1e3:.3f} ms)")
    print(f"  drift       {s['drift_ppm']:.3f} ppm  (1-sigma {s['drift_sigma_ppm']:.3f} ppm, "
          f"95% +-{s['drift_ci95_ppm']:.3f} ppm)")
    print(f"  taps {s['n_taps_detected']}, pulses {s['n_pulses']}, matched {s['n_matched']}, "
          f"inliers {s['n_inliers']}, outliers {s['n_outliers']}, taps without pulse "
          f"{s['n_taps_without_pulse']}, pulses without tap {s['n_pulses_without_tap']}")
    print(f"  residual std {s['residual_std_ms']:.3f} ms (outlier limit "
          f"{s['outlier_limit_ms']:.3f} ms)")
    for g in s["counter_gaps"]:
        print(f"  counter gap: {g['n_samples']} samples lost at row {g['row']}")
    for st in s["residual_steps"]:
        print(f"  residual step: {st['n_samples']} samples lost between counters "
              f"{st['bracket_counter'][0]:.0f} and {st['bracket_counter'][1]:.0f}")
    opts_json = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()
                 if k != "func"}
    try:
        write_results(path, res, counter, pulses, opts_json)
    except OSError as exc:
        raise RunFailure(f"{path}: cannot write /results/sync: {exc}") from None
    print(f"  wrote /results/sync to {path}")
    if args.plot_dir is not None:
        try:
            for p in plot(res, pulses, args.plot_dir):
                print(f"  plot {p}")
        except ImportError:
            print("  plots skipped: matplotlib is not installed (pip install rigctl[report])",
                  file=sys.stderr)
    return 0
