"""The report's plots (matplotlib, Agg backend; imported lazily). Field units on every axis.

Each ``plot_*`` function draws one PNG into the output directory and returns its path, or None
when the recording holds nothing to draw. :func:`make_plots` draws all of them and returns
{plot id: path} (ids: table_timeline, cal_residuals_orientation, cal_residuals_rate,
cal_rms, allan, sync_hist, sync_residual).
"""
from __future__ import annotations

import io
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..analysis.allan import DEV_UNITS
from ..analysis.allan_drift import plot_extras
from ..analysis.production import measured
from ..jsonable import jsonable
from ..recording.checkpoint import write_atomic
from ..sensor_axes import axis_name
from .report import RunData, find_session
from .report_allan import allan_curves

MG_PER_M_S2 = 1000.0 / 9.80665
DEG_H_PER_RAD_S = 180.0 / math.pi * 3600.0
DPI = 90
KIND_COLOURS = {"warmup": "#fde2b3", "orientation": "#cfe3f7", "rate": "#d9f2d0",
                "capture": "#eadcf5", "taps": "#f7d4d4", "wait": "#eeeeee"}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> Path:
    plt = _plt()
    fig.tight_layout()
    save_whole(fig, path, DPI)
    plt.close(fig)
    return path


def save_whole(fig: Any, path: Path, dpi: int) -> None:
    """``fig`` in ``path`` (the format its suffix names; PNG without one), whole or not at all:
    rendered in memory, then written by :func:`rigctl.recording.checkpoint.write_atomic`."""
    from matplotlib.layout_engine import PlaceHolderLayoutEngine

    # fig.tight_layout() leaves a placeholder layout engine, and savefig draws a figure with
    # any layout engine twice (once to lay it out, once to render); a placeholder lays out
    # nothing, so the first draw (a third of the save) is dropped: the same pixels, bytes
    if isinstance(fig.get_layout_engine(), PlaceHolderLayoutEngine):
        fig.set_layout_engine(None)
    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, format=path.suffix[1:].lower() or "png")
    write_atomic(path, buf.getvalue())


def _shade_segments(ax: Any, segments: dict[str, np.ndarray] | None) -> None:
    if not segments or "t_start" not in segments:
        return
    seen: set[str] = set()
    for k, a, b in zip(segments["kind"], segments["t_start"], segments["t_end"]):
        c = KIND_COLOURS.get(str(k), "#eeeeee")
        ax.axvspan(a, b, color=c, lw=0, label=None if k in seen else f"{k} window")
        seen.add(str(k))


def plot_table_timeline(data: RunData, out: Path) -> Path | None:
    """Gimbal angles (deg) and rates (deg/s) against run time (s); sampling windows shaded."""
    t = data.table
    if t is None or "angle" not in t or t["time"].size == 0:
        return None
    plt = _plt()
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(11, 5.5), sharex=True)
    names = ("outer", "middle", "inner")
    for ax, key, unit in ((a1, "angle", "deg"), (a2, "rate", "deg/s")):
        _shade_segments(ax, data.segments)
        v = np.degrees(np.unwrap(t[key], axis=0)) if key == "angle" else np.degrees(t[key])
        for i in range(3):  # angles unwrapped: a rate test is a straight ramp, not dots at +-180
            ax.plot(t["time"], v[:, i], lw=0.9, label=names[i])
        ax.set_ylabel(f"table {key} [{unit}]")
        ax.grid(True, lw=0.3)
    a1.legend(fontsize=7, ncol=6, loc="upper right")
    a2.set_xlabel("run time [s]")
    a1.set_title("Table orientation and rate (shaded: sampling windows by kind)")
    return _save(fig, out / "table_timeline.png")


def _residual_grid(cal: dict[str, Any], data: RunData) -> tuple[np.ndarray, np.ndarray, list[int]] | None:
    """(K, 6) residuals before and after (SI) and the /segments rows they belong to."""
    cl = cal.get("closed_loop") or {}
    dec, fin = cl.get("declared") or {}, cl.get("final") or {}
    rb, ra = dec.get("residuals"), fin.get("residuals")
    rows = data.cal_rows
    if rb is None or ra is None or not rows:
        return None
    rb = np.array([np.nan if v is None else v for v in rb], dtype=float)
    ra = np.array([np.nan if v is None else v for v in ra], dtype=float)
    if rb.size != 6 * len(rows) or ra.size != rb.size:
        return None
    return rb.reshape(-1, 6), ra.reshape(-1, 6), rows


def _mark_before_after(ax: Any, x: np.ndarray, before: np.ndarray, after: np.ndarray,
                       colour: str, label: str, dx: float = 0.0) -> None:
    """Before (open markers, shifted left by dx) and after (filled, shifted right)."""
    ax.plot(x - dx, before, "o", mfc="none", color=colour, ms=4, label=f"{label} before")
    ax.plot(x + dx, after, "o", color=colour, ms=3, label=f"{label} after")


def plot_cal_residuals_orientation(data: RunData, out: Path) -> Path | None:
    """Per-orientation residuals of the declared (before) and closed-loop (after) fits."""
    cal = find_session(data.results.get("calibration", {}).get("json"))
    grid = _residual_grid(cal, data) if cal else None
    if grid is None:
        return None
    rb, ra, rows = grid
    kinds = data.segments["kind"][rows]
    sel = np.flatnonzero(kinds == "orientation")
    if sel.size == 0:
        return None
    plt = _plt()
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(11, 6), sharex=True)
    x = np.arange(sel.size)
    cols = ("tab:blue", "tab:orange", "tab:green")
    for i in range(3):
        _mark_before_after(a1, x, rb[sel, i] * MG_PER_M_S2, ra[sel, i] * MG_PER_M_S2, cols[i],
                           axis_name("accel", i), 0.15)
        _mark_before_after(a2, x, rb[sel, 3 + i] * DEG_H_PER_RAD_S,
                           ra[sel, 3 + i] * DEG_H_PER_RAD_S, cols[i], axis_name("gyro", i), 0.15)
    a1.set_ylabel("accel residual [mg]")
    a2.set_ylabel("gyro residual [deg/h]")
    labels = [str(data.segments["label"][rows[j]]) for j in sel]
    a2.set_xticks(x)
    a2.set_xticklabels(labels, rotation=75, fontsize=6)
    a2.set_xlabel("orientation (segment)")
    for ax in (a1, a2):
        ax.axhline(0, color="k", lw=0.5)
        ax.grid(True, lw=0.3)
        ax.legend(fontsize=6, ncol=6)
    a1.set_title("Residuals per orientation: before (open, declared model) and after "
                 "(filled, closed loop)")
    return _save(fig, out / "cal_residuals_orientation.png")


def plot_cal_residuals_rate(data: RunData, out: Path) -> Path | None:
    """Per-rate residuals (gyro deg/h, accel mg) against the commanded rate (deg/s)."""
    cal = find_session(data.results.get("calibration", {}).get("json"))
    grid = _residual_grid(cal, data) if cal else None
    if grid is None:
        return None
    rb, ra, rows = grid
    seg = data.segments
    kinds = seg["kind"][rows]
    sel = np.flatnonzero(kinds == "rate")
    if sel.size == 0:
        return None
    rate = np.degrees(seg["commanded_rate"][[rows[j] for j in sel]])
    signed = rate[np.arange(sel.size), np.argmax(np.abs(rate), axis=1)]
    turning = np.argmax(np.abs(rate), axis=1)
    plt = _plt()
    fig, axes = plt.subplots(2, 3, figsize=(11, 6), sharex=True)
    cols = ("tab:blue", "tab:orange", "tab:green")
    for i in range(3):
        for r, (sensor, off, fac, unit) in enumerate((("gyro", 3, DEG_H_PER_RAD_S, "deg/h"),
                                                       ("accel", 0, MG_PER_M_S2, "mg"))):
            ax = axes[r, i]
            for g in range(3):
                m = turning == g
                if not np.any(m):
                    continue
                _mark_before_after(ax, signed[m], rb[sel[m], off + i] * fac,
                                   ra[sel[m], off + i] * fac, cols[g], f"turning {'xyz'[g]}", 3.0)
            ax.axhline(0, color="k", lw=0.5)
            ax.grid(True, lw=0.3)
            ax.set_title(axis_name(sensor, i), fontsize=9)
            ax.set_ylabel(f"{axis_name(sensor, i)} residual [{unit}]", fontsize=8)
            if r == 1:
                ax.set_xlabel("commanded rate [deg/s]")
    axes[0, 0].legend(fontsize=6)
    fig.suptitle("Residuals per rate: before (open) and after (filled) the closed loop", fontsize=10)
    return _save(fig, out / "cal_residuals_rate.png")


def plot_cal_rms(data: RunData, out: Path) -> Path | None:
    """Residual RMS per channel before and after, against the noise floor (mg, deg/h)."""
    cal = find_session(data.results.get("calibration", {}).get("json"))
    table = ((cal or {}).get("closed_loop") or {}).get("rms_table") or []
    rows = [r for r in table if r.get("channel") != "all"]
    if not rows:
        return None
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.6))
    for ax, unit, title in ((axes[0], "mg", "accelerometer"), (axes[1], "deg_h", "gyro")):
        sub = [r for r in rows if r.get("unit") == unit]
        if not sub:
            ax.set_visible(False)
            continue
        x = np.arange(len(sub))
        w = 0.27
        for j, (key, lab, col) in enumerate((("noise_floor", "noise floor", "0.6"),
                                            ("rms_before", "RMS before", "tab:red"),
                                            ("rms_after", "RMS after", "tab:green"))):
            vals = [r.get(f"{key}_{unit}") or 0.0 for r in sub]
            ax.bar(x + (j - 1) * w, vals, w, label=lab, color=col)
        ax.set_xticks(x)
        ax.set_xticklabels([r["channel"] for r in sub])
        ax.set_ylim(bottom=0)  # linear axis from zero: bar lengths compare
        ax.set_ylabel(f"residual RMS [{unit.replace('deg_h', 'deg/h')}]")
        ax.set_title(title)
        ax.grid(True, axis="y", which="both", lw=0.3)
        ax.legend(fontsize=7)
    return _save(fig, out / "cal_rms.png")


#: reference slopes drawn on every Allan plot (IEEE 952: Q, N, B, K, R)
GUIDE_SLOPES = ((-1.0, "-1 (Q)"), (-0.5, "-1/2 (N)"), (0.0, "0 (B)"), (0.5, "+1/2 (K)"),
                (1.0, "+1 (R)"))


def _allan_ylim(dev: np.ndarray, lo95: np.ndarray | None, hi95: np.ndarray | None
                ) -> tuple[float | None, float | None]:
    """The Allan plot's y range: half the lowest band point to twice the highest (None: none)."""
    with np.errstate(invalid="ignore"):
        lo = np.nanmin(lo95 if lo95 is not None else dev) if np.size(dev) else np.nan
        hi = np.nanmax(hi95 if hi95 is not None else dev) if np.size(dev) else np.nan
    if np.isfinite(lo) and np.isfinite(hi) and lo > 0:
        return float(lo) / 2.0, float(hi) * 2.0
    return None, None


def _guide_label_at(slope: float, t_a: float, d_a: float, span: np.ndarray,
                    y_lo: float | None, y_hi: float | None) -> tuple[float, float] | None:
    """Where a slope guide d_a (tau / t_a)^slope is labelled: the flat guide at its left end; a
    falling one at the last tau it is inside the plot (where it leaves through the bottom, or
    the span's end), a rising one at the first (where it enters through the bottom); each a
    hair inside the y range. None when no part of it is inside."""
    t0, t1 = float(span[0]), float(span[-1])
    if y_lo is None:
        return (t0, d_a) if slope >= 0 else (t1, d_a * (t1 / t_a) ** slope)
    lo_in, hi_in = y_lo * (y_hi / y_lo) ** 0.01, y_hi * (y_lo / y_hi) ** 0.01
    if slope == 0:
        return (t0, d_a) if lo_in <= d_a <= hi_in else None
    # the taus where the guide is between lo_in and hi_in, within the span
    ta, tb = sorted((t_a * (lo_in / d_a) ** (1.0 / slope), t_a * (hi_in / d_a) ** (1.0 / slope)))
    a, b = max(t0, ta), min(t1, tb)
    if not a <= b:
        return None
    t = b if slope < 0 else a
    return t, d_a * (t / t_a) ** slope


def draw_allan_axis(ax: Any, tau: np.ndarray, dev: np.ndarray, fit: dict[str, Any] | None,
                    sensor: str, unit: str, fac: float, title: str,
                    lo68: np.ndarray | None = None, hi68: np.ndarray | None = None,
                    lo95: np.ndarray | None = None, hi95: np.ndarray | None = None,
                    extras: list[tuple[str, np.ndarray, np.ndarray]] | None = None) -> None:
    """One Allan plot, as ``rigctl allan --plot`` and the report draw it: the deviation (field
    unit) with 68 % bars and the 95 % band, the slope guides -1, -1/2, 0, +1/2, +1 (grey), each
    fitted term (dashed, value in the legend) and each bounded N/B/K at its bound (dotted), the
    fitted total (black), and the taus where the self-check finds the total outside the band
    (red rings). ``extras``: (label, tau, deviation in SI) of features found before the fit
    that are not IEEE 952 terms (a warm-up transient, a temperature term), dash-dotted."""
    from ..solvers import allan_fit as F
    from ..solvers import noise_coefficients as NC

    tau = np.asarray(tau, dtype=float)
    dev = np.asarray(dev, dtype=float)
    if lo95 is not None and hi95 is not None:
        ax.fill_between(tau, lo95, hi95, color="tab:blue", alpha=0.15, lw=0, label="95 % band")
    if lo68 is not None and hi68 is not None:
        ax.errorbar(tau, dev, yerr=[dev - np.asarray(lo68), np.asarray(hi68) - dev], fmt=".",
                    ms=3, lw=0.7, color="tab:blue", label="overlapping ADEV, 68 %")
    else:
        ax.plot(tau, dev, ".", color="tab:blue", label="overlapping ADEV")
    ok = np.isfinite(dev) & (dev > 0)
    y_lo, y_hi = _allan_ylim(dev, lo95, hi95)
    if np.any(ok):  # slope guides: -1, -1/2 through the first point; 0, +1/2, +1 the minimum
        t_ok, d_ok = tau[ok], dev[ok]
        i_min = int(np.argmin(d_ok))
        span = np.array([t_ok[0], t_ok[-1]])
        row = 0
        for slope, label in GUIDE_SLOPES:
            t_a, d_a = (t_ok[0], d_ok[0]) if slope < 0 else (t_ok[i_min], d_ok[i_min])
            ys = d_a * (span / t_a) ** slope
            ax.plot(span, ys, ":", color="0.55", lw=0.7, zorder=0)
            at = _guide_label_at(slope, t_a, d_a, span, y_lo, y_hi)
            if at is None:  # the guide is outside the plotted range
                continue
            # each label on its own row of 7 points above its anchor (a falling guide's where
            # it leaves the plot, a rising one's where it enters; the flat one at its left
            # end), so that labels of guides meeting in one point do not overprint
            ax.annotate(f"slope {label}", at, fontsize=5.5, color="0.4",
                        ha="right" if slope < 0 else "left", va="bottom",
                        xytext=(-2 if slope < 0 else 2, 1 + (0 if slope == 0 else 7 * row)),
                        textcoords="offset points", annotation_clip=True,
                        bbox={"fc": "white", "ec": "none", "alpha": 0.7, "pad": 0.4})
            row += slope != 0
    fit = fit or {}
    co = NC.as_coefficients(fit["coefficients"]) if fit.get("coefficients") else None
    coeff = {t: v**2 for t, v in NC.resolved_values(co).items() if v > 0} if co else {}
    tt = np.logspace(np.log10(tau.min()), np.log10(tau.max()), 200)
    cols = F.design_matrix(tt)
    total = np.zeros_like(tt)
    for j, term in enumerate(F.TERMS):
        c2 = float(coeff.get(term) or 0.0)
        unit_f, ffac = F.FIELD_UNITS[sensor][term]
        if c2 > 0:
            part = cols[:, j] * c2
            total += part
            ax.plot(tt, np.sqrt(part) * fac, "--", lw=0.9,
                    label=f"{term} {math.sqrt(c2) * ffac:.3g} {unit_f}")
        elif term in ("N", "B", "K") and co and not getattr(co, term).resolved:
            ub = getattr(co, term).upper95
            if ub and math.isfinite(ub) and ub > 0:
                ax.plot(tt, np.sqrt(cols[:, j]) * ub * fac, ":", lw=0.9,
                        label=f"{term} < {ub * ffac:.3g} {unit_f} (bound)")
    for g in (co.gm if co else ()):  # the fit's Gauss-Markov term (allan_fit: gm_term)
        if g.sigma.resolved and g.sigma.value > 0:
            part = F.gm_column(tt, g.tau_c_s) * g.sigma.value ** 2
            total += part
            coeff = coeff or {"GM": g.sigma.value ** 2}
            unit_f, ffac = F.FIELD_UNITS[sensor]["B"]
            ax.plot(tt, np.sqrt(part) * fac, "--", lw=0.9,
                    label=f"GM {g.sigma.value * ffac:.3g} {unit_f}, Tc {g.tau_c_s:.3g} s")
    if coeff:
        ax.plot(tt, np.sqrt(total) * fac, "k-", lw=1.2, label="fitted total")
    tones = (fit.get("tones") or {}).get("terms") or []
    if tones and tau.size and tau.min() > 0:
        # the tones' Allan term exists at the curve's own taus (m tau0) only, and oscillates
        # with m: drawn there, with the total it is part of in the fitted model
        from ..solvers import allan_tones as TN

        tau0 = float(fit["tones"].get("tau0_s") or tau.min())
        m = np.maximum(1.0, np.round(tau / tau0))
        t2 = TN.tones_avar(tau0, m, tones)
        keep = t2 > 0
        freqs = ", ".join(f"{t['freq_hz']:.4g}" for t in tones)
        ax.plot(tau[keep], np.sqrt(t2[keep]) * fac, "x", ms=3, color="tab:purple",
                label=f"tones ({freqs} Hz)")
        tot_t = F.fitted_avar(fit, tau) + t2
        ax.plot(tau, np.sqrt(tot_t) * fac, "-", color="tab:purple", lw=0.8,
                label="fitted total with tones")
    for label, t_x, d_x in extras or []:
        t_x, d_x = np.asarray(t_x, dtype=float), np.asarray(d_x, dtype=float)
        keep = np.isfinite(d_x) & (d_x > 0)
        if np.any(keep):
            ax.plot(t_x[keep], d_x[keep] * fac, "-.", lw=0.9, label=label)
    check = fit.get("check") or {}
    marked = np.zeros(tau.size, dtype=bool)
    for o in check.get("outside") or []:
        marked |= (tau >= o["tau_from_s"]) & (tau <= o["tau_to_s"])
    if np.any(marked):
        ax.plot(tau[marked], dev[marked], "o", mfc="none", mec="tab:red", ms=5, mew=0.8,
                label="fit outside the 95 % band")
    ax.set_xscale("log")
    ax.set_yscale("log")
    if y_lo is not None:
        ax.set_ylim(y_lo, y_hi)
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("tau [s]")
    ax.set_ylabel(f"Allan deviation [{unit}]")
    ax.grid(True, which="both", lw=0.3)
    ax.legend(fontsize=6)


def plot_allan(data: RunData, out: Path, log: Callable[..., None] | None = None) -> Path | None:
    """Allan deviation per axis (:func:`draw_allan_axis`)."""
    curves = allan_curves(data, log)
    if not curves:
        return None
    plt = _plt()
    names = list(curves)
    ncol = 2 if len(names) > 1 else 1
    nrow = math.ceil(len(names) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(11, 3.3 * nrow), squeeze=False)
    order = sorted(names, key=lambda a: ("g" not in a[0], a))
    gyro = [a for a in order if curves[a]["sensor"] == "gyro"]
    accel = [a for a in order if curves[a]["sensor"] != "gyro"]
    slots = []
    for r in range(nrow):
        for c, lst in enumerate((gyro, accel) if ncol == 2 else (order,)):
            slots.append((axes[r, c], lst[r] if r < len(lst) else None))
    for ax, name in slots:
        if name is None:
            ax.set_visible(False)
            continue
        cv = curves[name]
        draw_allan_axis(ax, cv["tau_s"], cv["adev"], cv.get("fit"), cv["sensor"], cv["unit"],
                        cv["factor"],
                        f"{name} ({cv['sensor']}){' - quick curve' if cv.get('quick') else ''}",
                        cv.get("lo68"), cv.get("hi68"), cv.get("lo95"), cv.get("hi95"))
    return _save(fig, out / "allan.png")


def plot_allan_result(result: dict[str, Any], out_path: str | Path) -> None:
    """``rigctl allan --plot FILE``: one log-log plot per axis of a fresh Allan result
    (rigctl.analysis.allan.compute; :func:`draw_allan_axis`: 68 % bars, 95 % band, slope guides,
    fitted terms and bounds, fitted total, taus where the fit leaves the band)."""
    plt = _plt()
    axes = list(result["axes"].items())
    fig, subs = plt.subplots(len(axes), 1, figsize=(7, 3.4 * len(axes)), squeeze=False)
    for ax, (name, r) in zip(subs[:, 0], axes):
        unit, fac = DEV_UNITS[r["sensor"]]
        draw_allan_axis(ax, r["tau_s"], r[f"adev_{unit}"], jsonable(r["fit"], keep_nonfinite=True),
                        r["sensor"], unit, fac,
                        f"{name} ({r['sensor']})", r[f"lo68_{unit}"], r[f"hi68_{unit}"],
                        r[f"lo95_{unit}"], r[f"hi95_{unit}"], extras=plot_extras(r))
    fig.tight_layout()
    save_whole(fig, Path(out_path), 120)
    plt.close(fig)


def plot_batch_summary(results: list[dict[str, Any]], lots: dict[str, str], out: Path, spec: Any) -> Path | None:
    """``rigctl batch``: each specified (or the first 12) parameter across units, per lot: value
    with its 95 % interval, and the spec's limits; batch.png in ``out``. None without
    matplotlib or without a parameter to draw."""
    try:
        plt = _plt()
    except ImportError:
        return None
    series: dict[str, list[tuple[str, int, float, float, float, Any]]] = {}
    for i, r in enumerate(x for x in results if x["ok"]):
        for kind, payload in r["results"].items():
            for m in measured(kind, payload):
                d = m.display
                lo, hi = m.interval
                series.setdefault(d.base, []).append((lots[r["recording"]], i, d.value(m.value),
                                                      d.value(lo), d.value(hi), d))
    names = [n for n in series if spec is None or spec.limit_for(n) is not None][:12] if series else []
    if not names:
        return None
    ncol = 3
    nrow = -(-len(names) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(11, 2.6 * nrow), squeeze=False)
    for ax, name in zip(axes.flat, names):
        pts = series[name]
        d = pts[0][5]
        for lot in sorted({p[0] for p in pts}):
            sel = [p for p in pts if p[0] == lot]
            x = [p[1] for p in sel]
            y = [p[2] for p in sel]
            err = [[p[2] - p[3] for p in sel], [p[4] - p[2] for p in sel]]
            ax.errorbar(x, y, yerr=err, fmt="o", ms=3, lw=0.8, label=f"lot {lot}")
        lim = spec.limit_for(name) if spec is not None else None
        if lim is not None:
            for v in lim.si(d):
                if v is not None:
                    ax.axhline(d.value(v), color="tab:red", lw=0.8, ls="--")
        ax.set_title(name, fontsize=8)
        ax.set_ylabel(f"[{d.unit}]", fontsize=8)
        ax.set_xlabel("recording", fontsize=7)
        ax.tick_params(labelsize=7)
        ax.grid(True, lw=0.3)
    for ax in list(axes.flat)[len(names):]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=6)
    fig.suptitle("Parameters across units (95 % intervals; dashed: spec limits)", fontsize=10)
    fig.tight_layout()
    path = out / "batch.png"
    save_whole(fig, path, 90)
    plt.close(fig)
    return path


def _sync_errors_ms(arr: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray, str] | None:
    if "pulse_time" not in arr or arr["pulse_time"].size == 0:
        return None
    inl = arr.get("inlier", np.ones(arr["pulse_time"].size)).astype(bool)
    if "tap_reference_time" in arr:
        err = (arr["pulse_time"] - arr["tap_reference_time"]) * 1e3
        what = "pulse - clock(tap)"
    elif "local_residual" in arr:
        err = arr["local_residual"] * 1e3
        what = "local matching residual"
    else:
        return None
    return arr["pulse_time"], err, inl, what


def draw_sync_hist(arrays: dict[str, np.ndarray], summary: dict[str, Any], out: Path) -> Path | None:
    """Histogram of the tap matching error (ms), as the paper's figure 7, from the datasets and
    summary of /results/sync (:func:`rigctl.analysis.sync.result_arrays`)."""
    got = _sync_errors_ms(arrays)
    if got is None:
        return None
    _, err, inl, what = got
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 3.8))
    bins = np.histogram_bin_edges(err[inl], bins=min(40, max(5, int(inl.sum() // 3))))
    ax.hist(err[inl], bins=bins, color="tab:blue", label=f"inliers ({int(inl.sum())})")
    if (~inl).any():
        ax.hist(np.clip(err[~inl], bins[0], bins[-1]), bins=bins, color="tab:red",
                label=f"outliers ({int((~inl).sum())}, clipped to range)")
    std = summary.get("residual_std_ms")
    ax.set_title(f"Tap matching error ({summary.get('timing', '?')} timing"
                 + (f", std {std:.3f} ms)" if isinstance(std, (int, float)) else ")"), fontsize=10)
    ax.set_xlabel(f"matching error: {what} [ms]")
    ax.set_ylabel("taps [count]")
    ax.grid(True, lw=0.3)
    ax.legend(fontsize=7)
    return _save(fig, out / "sync_hist.png")


def draw_sync_residual(arrays: dict[str, np.ndarray], out: Path) -> Path | None:
    """Clock residual (ms) against reference time (s), from the datasets of /results/sync."""
    got = _sync_errors_ms(arrays)
    if got is None:
        return None
    t, err, inl, what = got
    plt = _plt()
    fig, ax = plt.subplots(figsize=(11, 3.6))
    ax.plot(t[inl], err[inl], "o", ms=3, label="inliers")
    if (~inl).any():
        ax.plot(t[~inl], err[~inl], "x", color="tab:red", label="outliers")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("reference time [s]")
    ax.set_ylabel(f"clock residual ({what}) [ms]")
    ax.set_title("IMU clock residual against time")
    ax.grid(True, lw=0.3)
    ax.legend(fontsize=7)
    return _save(fig, out / "sync_residual.png")


def plot_sync_hist(data: RunData, out: Path) -> Path | None:
    """The recording's tap matching error histogram (:func:`draw_sync_hist`)."""
    sync = data.results.get("sync", {})
    return draw_sync_hist(sync.get("arrays") or {}, sync.get("json") or {}, out)


def plot_sync_residual(data: RunData, out: Path) -> Path | None:
    """The recording's clock residual against time (:func:`draw_sync_residual`)."""
    return draw_sync_residual(data.results.get("sync", {}).get("arrays") or {}, out)


# ------------------------------------------------------------------------------- thermal
_HEAT, _COOL = "tab:red", "tab:blue"


def _thermal(data: RunData) -> tuple[dict[str, Any], dict[str, np.ndarray]] | None:
    r = data.results.get("thermal") or {}
    payload, arrays = r.get("json") or {}, r.get("arrays") or {}
    if payload.get("mode") != "thermal" or "accel_window_temperature" not in arrays:
        return None
    return payload, arrays


def plot_thermal_parameters(data: RunData, out: Path) -> Path | None:
    """Bias and scale error against temperature per axis: the fitted polynomial with its 95 %
    band (from the coefficients' covariance), and for the bias each window's partial residual
    (residual + fitted bias), heating windows red, cooling blue."""
    got = _thermal(data)
    if got is None:
        return None
    payload, arr = got
    from ..display_units import display

    ref = float(payload.get("reference_c", 25.0))
    plt = _plt()
    fig, axes = plt.subplots(4, 3, figsize=(12, 11))
    for r0, sensor in ((0, "accel"), (2, "gyro")):
        T = np.asarray(arr[f"{sensor}_window_temperature"], float)
        heat = np.asarray(arr[f"{sensor}_window_heating"]).astype(bool)
        res = np.asarray(arr[f"{sensor}_residual_after"], float)
        grid = np.linspace(T.min(), T.max(), 120)
        u = "m_s2" if sensor == "accel" else "rad_s"
        for i, a in enumerate("xyz"):
            names = [str(n) for n in arr[f"{sensor}_names_{a}"]]
            cov = np.asarray(arr[f"{sensor}_cov_{a}"], float)
            vals = {q["name"]: q["value"] for q in payload["sensors"][sensor]["parameters"]}
            for row, prefix, off, what in ((r0, f"{sensor}_bias_{a}_{u}", 0.0, "bias"),
                                           (r0 + 1, f"{sensor}_scale_{a}_per_K", 1.0, "scale error")):
                base = prefix if what == "bias" else f"{sensor}_M_{a}{a}_ratio"
                per = prefix + "_per_K" if what == "bias" else prefix
                idx, powers = [], []
                for j, n in enumerate(names):
                    if n == base:
                        idx.append(j), powers.append(0)
                    elif n.startswith(per) and n[len(per):] in ("", "2", "3", "4", "5"):
                        idx.append(j), powers.append(int(n[len(per):] or 1))
                if not idx:
                    continue
                d = display(f"{sensor}_bias_x_{u}") if what == "bias" else display("accel_scale_x_per_K")
                fac = d.factor
                J = np.column_stack([(grid - ref) ** p for p in powers])
                coef = np.array([vals[names[j]] for j in idx])
                fit = J @ coef - off
                band = 1.96 * np.sqrt(np.einsum("ij,jk,ik->i", J, cov[np.ix_(idx, idx)], J))
                ax = axes[row, i]
                ax.fill_between(grid, (fit - band) * fac, (fit + band) * fac, color="0.8", lw=0, label="95 % band")
                ax.plot(grid, fit * fac, color="k", lw=1, label="fit")
                if what == "bias":
                    Jw = np.column_stack([(T - ref) ** p for p in powers])
                    pts = (Jw @ coef + res[:, i]) * fac
                    ax.plot(T[heat], pts[heat], ".", color=_HEAT, ms=3, label="heating")
                    ax.plot(T[~heat], pts[~heat], ".", color=_COOL, ms=3, label="cooling")
                unit = d.unit.replace("/K", "") if what == "bias" else "ppm"
                ax.set_title(f"{axis_name(sensor, i)} {what}", fontsize=9)
                ax.set_ylabel(f"[{unit}]", fontsize=8)
                ax.set_xlabel("IMU temperature [degC]", fontsize=8)
                ax.grid(True, lw=0.3)
                if i == 0:
                    ax.legend(fontsize=6)
    return _save(fig, out / "thermal_parameters.png")


def plot_thermal_residuals(data: RunData, out: Path) -> Path | None:
    """Window residuals against temperature with one calibration at the reference temperature
    (before) and with the thermal model (after); heating red, cooling blue."""
    got = _thermal(data)
    if got is None:
        return None
    payload, arr = got
    plt = _plt()
    fig, axes = plt.subplots(2, 3, figsize=(12, 6))
    for r, sensor, fac, unit in ((0, "accel", MG_PER_M_S2, "mg"), (1, "gyro", DEG_H_PER_RAD_S, "deg/h")):
        T = np.asarray(arr[f"{sensor}_window_temperature"], float)
        heat = np.asarray(arr[f"{sensor}_window_heating"]).astype(bool)
        before = np.asarray(arr[f"{sensor}_residual_before"], float) * fac
        after = np.asarray(arr[f"{sensor}_residual_after"], float) * fac
        for i in range(3):
            ax = axes[r, i]
            for m, col, lab in ((heat, _HEAT, "heating"), (~heat, _COOL, "cooling")):
                ax.plot(T[m], before[m, i], "x", color=col, ms=3, alpha=0.35, label=f"before, {lab}")
                ax.plot(T[m], after[m, i], ".", color=col, ms=3, label=f"after, {lab}")
            ax.axhline(0, color="k", lw=0.5)
            ax.set_title(f"{axis_name(sensor, i)}: residuals", fontsize=9)
            ax.set_ylabel(f"[{unit}]", fontsize=8)
            ax.set_xlabel("IMU temperature [degC]", fontsize=8)
            ax.grid(True, lw=0.3)
            if i == 0:
                ax.legend(fontsize=6)
    return _save(fig, out / "thermal_residuals.png")


def make_plots(data: RunData, out: Path, log: Callable[..., None] | None = None
               ) -> dict[str, Path]:
    """Draw every plot the recording supports; {plot id: PNG path}."""
    got = {
        "table_timeline": plot_table_timeline(data, out),
        "cal_residuals_orientation": plot_cal_residuals_orientation(data, out),
        "cal_residuals_rate": plot_cal_residuals_rate(data, out),
        "cal_rms": plot_cal_rms(data, out),
        "allan": plot_allan(data, out, log),
        "sync_hist": plot_sync_hist(data, out),
        "sync_residual": plot_sync_residual(data, out),
        "thermal_parameters": plot_thermal_parameters(data, out),
        "thermal_residuals": plot_thermal_residuals(data, out),
    }
    return {k: v for k, v in got.items() if v is not None}
