"""Issue 15's first Done-when on every emulator profile and every real capture in the tests.

For each case the script writes a rigctl recording and runs the Allan pipeline as `rigctl allan`
does (rigctl.analysis.allan.compute: streamed deviations, noise ID, EDF bands, the joint IEEE 952
fit and its self-check), once per tau set (--taus octave, all and the default 95), then checks,
with numbers read here from the curve and not from the fit's own bookkeeping:

  bounds  no term given as a bound exceeds what the curve allows: B <= min sigma / 0.664,
          N <= min sigma sqrt(tau), K <= min sigma sqrt(3/tau), Q <= min sigma tau / sqrt(3),
          R <= min sigma sqrt(2) / tau (each term adds a non-negative part to sigma^2), the
          minimum taken over the informative taus (95 % band hi95 <= 2 lo95, i.e. EDF >= 16.95:
          the true sigma within 0.75 .. 1.50 x the measured one; a tau of a handful of averages,
          EDF 3: 0.57 .. 3.6 x, limits nothing). Also counted: bounds above the same limits
          taken over every tau (``over_all_taus``), i.e. where such a tau is lower, and, as
          Done-when item 1 words it, bounds above the measured point limits over the
          informative taus (column over_pt, ``bounds_above_point_limit_*``, with the largest
          bound / limit per term): the limit the first count applies where the fit needs a
          model error of 5 % or more, without the curve's chi-square allowance elsewhere.
  band    the fitted total (sigma^2 = 3Q^2/tau^2 + N^2/tau + (2 ln2/pi) B^2 + K^2 tau/3 +
          R^2 tau^2/2, from the fitted values) lies inside the curve's 95 % band at every
          informative tau (hi95 <= 2 lo95), or the tau is named by the self-check (a warning
          when the check fails, a note when the few taus outside are chance; departures under
          10 % in one sentence). Counted: taus outside the band; of them, not named; fits
          whose check failed (a warning naming the taus).
  taus    octave and all agree: for every term, both supported and their 95 % intervals
          overlap, or one is a bound and the other's interval starts below it, or both bounds.

Cases: the emulator's default IMU (configs/sim.yaml, the declared model with B and K) and every
profile of configs/imu-profiles.yaml (full error model: front end, quantization, warm-up, clock
with dropped samples -- gaps, skipped as Stable32 does), static (gravity up, Earth rate at 45
deg), --hours each (default 12) at the profile's rate, captured as procedures/allan-overnight.yaml
does: after its 15-minute warm-up (--warmup-s, default 900: the capture starts 900 s after
power-on; 0 captures from power-on, the warm-up's thermal transient then in the curve -- on
consumer_mems gx, 4e-3 rad/s decaying with 270 s, ~13 deg/h of Allan deviation at 300 s, above
its 6.6 deg/h floor); and the real captures in tests/data
(ADIS16405 2.8 h, XSens MTi-G gyro 1.4 h), imported with `rigctl import` from whitespace text.

Prints a table per case and axis, then one JSON line (counts over every case, axis and tau set).
"""
from __future__ import annotations

import argparse
import gzip
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "tests" / "data"
OMEGA = 7.292115e-5
LAT = math.radians(45.0)
G0 = 9.80665
TAU_SETS = ("octave", "all", 95)
B_FACTOR = math.sqrt(2.0 * math.log(2.0) / math.pi)  # 0.664


def _load() -> str:
    return "/".join(f"{v:.2f}" for v in os.getloadavg())


# ------------------------------------------------------------------ recordings
def _h5(path: Path, fs: float) -> tuple:
    import h5py

    from rigctl.recording.recorder import FORMAT_NAME, SCHEMA_VERSION, STATUS_DTYPE

    f = h5py.File(path, "w")
    f.attrs["format"] = FORMAT_NAME
    f.attrs["schema_version"] = SCHEMA_VERSION
    f.create_dataset("run/status", data=np.array([b"complete"], dtype=STATUS_DTYPE))
    imu = f.create_group("imu")
    imu.attrs["sample_rate_hz"] = fs
    ds = {}
    for name, shape, dt, unit in (("time", (), "f8", "s"), ("counter", (), "u8", "1"),
                                  ("angular_rate", (3,), "f8", "rad/s"),
                                  ("specific_force", (3,), "f8", "m/s^2")):
        d = imu.create_dataset(name, (0, *shape), dt, maxshape=(None, *shape),
                               chunks=(8192, *shape))
        d.attrs["units"] = unit
        ds[name] = d
    return f, ds


def _append(ds: dict, **cols: np.ndarray) -> None:
    for k, v in cols.items():
        d = ds[k]
        n0 = d.shape[0]
        d.resize(n0 + len(v), axis=0)
        d[n0:] = v


#: procedures/warmup.yaml's default (15 min): allan-overnight.yaml captures after it
WARMUP_S = 900.0


def emulated_recording(case: str, path: Path, hours: float, seed: int = 1,
                       warmup_s: float = WARMUP_S, overrides: Any = None) -> dict:
    """A static capture of ``hours`` from the emulator (``case``: 'default' or a profile),
    starting ``warmup_s`` after power-on (the profiles' warm-up; the default IMU has none).
    ``overrides``: changes to the profile, as imu.sim.overrides (ImuProfile.with_overrides)."""
    from rigctl.sim.imu import build_imu_model
    from rigctl.yamlio import load_file

    if case == "default":
        cfg = load_file(ROOT / "configs" / "sim.yaml")
        fs = float(cfg["imu"]["rate_hz"])
        model = build_imu_model(cfg["imu"]["sim"], fs, seed)
        full = False
    else:
        from rigctl.sim.error_model import ImuErrorModel
        from rigctl.sim.profiles import get_profile

        prof = get_profile(case).with_overrides({"power_on_time_s": float(warmup_s), **(overrides or {})})
        model = ImuErrorModel.from_profile(prof, seed=seed)
        fs = model.output_rate_hz
        full = True
    n = int(round(hours * 3600 * fs))
    chunk = 1 << 16
    f_up = np.array([0.0, 0.0, G0])
    w_e = np.array([0.0, OMEGA * math.cos(LAT), OMEGA * math.sin(LAT)])
    f, ds = _h5(path, fs)
    done, dropped = 0, 0
    try:
        while done < n:
            m = min(chunk, n - done)
            if full:
                g = model.sample_grid(m)
                k = g.t_internal.size
                F, W, _ = model.apply(g.t_internal, np.tile(f_up, (k, 1)), np.tile(w_e, (k, 1)))
                keep = g.keep
                _append(ds, time=g.t_out[keep], counter=g.counter[keep],
                        angular_rate=W[keep], specific_force=F[keep])
                dropped += int((~keep).sum())
            else:
                t = (done + np.arange(m)) / fs
                F, W, _ = model.apply(t, np.tile(f_up, (m, 1)), np.tile(w_e, (m, 1)))
                _append(ds, time=t, counter=np.arange(done, done + m, dtype=np.uint64),
                        angular_rate=W, specific_force=F)
            done += m
    finally:
        f.close()
    return {"rate_hz": fs, "samples": n, "dropped": dropped,
            "axes": ["gx", "gy", "gz", "ax", "ay", "az"]}


def _run_import(argv: list[str]) -> None:
    """`rigctl import ...` as the command line runs it (exit code checked)."""
    from rigctl import cli

    code = cli.main(["import", *argv, "--force"])  # its own directory: a kept run rewrites
    if code != 0:
        raise RuntimeError(f"rigctl import {' '.join(argv)}: exit {code}")


def real_recordings(tmp: Path) -> list[tuple[str, Path, dict]]:
    """The real captures of tests/data, written as whitespace text and imported with `rigctl
    import` (as a stranger's capture would be)."""
    out = []
    adis = DATA / "adis16405-static"
    if (adis / "gyro_counts.txt.gz").is_file():
        g = np.loadtxt(gzip.open(adis / "gyro_counts.txt.gz", "rt"), dtype=np.int64)
        a = np.loadtxt(gzip.open(adis / "accel_counts.txt.gz", "rt"), dtype=np.int64)
        txt = tmp / "adis16405.txt"
        with open(txt, "w") as fh:  # no header, no time column: --rate
            for row in np.column_stack([g, a]):
                fh.write(" ".join(str(int(v)) for v in row) + "\n")
        rec = tmp / "adis16405.h5"
        _run_import([str(txt), "-o", str(rec), "--rate", "100",
                     "--columns", "gyr_x=0,gyr_y=1,gyr_z=2,acc_x=3,acc_y=4,acc_z=5",
                     "--units", "gyr=counts:0.05 deg/s,acc=counts:0.00333 g"])
        out.append(("adis16405 (real)", rec, {"axes": ["gx", "gy", "gz", "ax", "ay", "az"],
                                              "datasheet": "gyro B 25.2 deg/h (in-run)"}))
    mtig = DATA / "mtig-static-contaminated" / "gyro_x_rad_s.txt.gz"
    if mtig.is_file():
        y = np.loadtxt(gzip.open(mtig, "rt"))
        txt = tmp / "mtig.tsv"
        with open(txt, "w") as fh:  # a header and a time column in ns, tab-separated
            fh.write("t_ns\tgyro_x\n")
            for i, v in enumerate(y):
                fh.write(f"{i * 10_000_000}\t{v:.8g}\n")
        rec = tmp / "mtig.h5"
        _run_import([str(txt), "-o", str(rec), "--columns", "time=t_ns,gyr_x=gyro_x",
                     "--units", "gyr=rad/s,time=ns"])
        out.append(("mtig (real)", rec, {"axes": ["gx"]}))
    astro = DATA / "astropi-sensehat-static" / "astro_pi_data_20150824_085954.csv.gz"
    if astro.is_file():  # the x-up section (58 h, a reading every ~10 s; README there)
        import csv
        import datetime as dt

        with gzip.open(astro, "rt", newline="") as fh:
            rows = list(csv.DictReader(fh))[3902:]
        t0 = dt.datetime.fromisoformat(rows[0]["time_stamp"]).timestamp()
        txt = tmp / "astropi.csv"
        with open(txt, "w") as fh:  # numeric time (the source's is a date), columns unchanged
            fh.write("t,temp_h,accel_x,accel_y,accel_z,gyro_x,gyro_y,gyro_z\n")
            for r in rows:  # with the board temperature: the pipeline checks the drift on it
                t = dt.datetime.fromisoformat(r["time_stamp"]).timestamp() - t0
                fh.write(f"{t:.0f},{r['temp_h']},{r['accel_x']},{r['accel_y']},{r['accel_z']},"
                         f"{r['gyro_x']},{r['gyro_y']},{r['gyro_z']}\n")
        seg = tmp / "astropi_sections.json"  # one static section: the whole of it
        seg.write_text(json.dumps({"x up": {"start": 0, "end": len(rows)}}))
        rec = tmp / "astropi.h5"
        _run_import([str(txt), "-o", str(rec), "--columns",
                     "time=t,temp=temp_h,acc_x=accel_x,acc_y=accel_y,acc_z=accel_z,gyr_x=gyro_x,"
                     "gyr_y=gyro_y,gyr_z=gyro_z", "--units", "acc=g,gyr=rad/s,time=s",
                     "--segments", str(seg)])
        out.append(("astropi sense hat (real)", rec,
                    {"axes": ["gx", "gy", "gz", "ax", "ay", "az"],
                     "datasheet": "gyro bias tracked by RTIMULib (100 s)"}))
    return out


# ------------------------------------------------------------------ checks
def limits_from_curve(tau: np.ndarray, dev: np.ndarray) -> dict[str, float]:
    """Each term's largest value the curve allows (SI), read here from the deviations."""
    return {"Q": float(np.min(dev * tau / math.sqrt(3.0))),
            "N": float(np.min(dev * np.sqrt(tau))),
            "B": float(np.min(dev)) / B_FACTOR,
            "K": float(np.min(dev * np.sqrt(3.0 / tau))),
            "R": float(np.min(dev * math.sqrt(2.0) / tau))}


def total_sigma(tau: np.ndarray, fit: dict, sensor: str, m: np.ndarray | None = None) -> np.ndarray:
    """The fitted total (SI) from the supported terms' values, plus the Allan variance of each
    tone the pipeline found and carried in its model (fit["tones"]: frequency f, amplitude a),
    written out here for the sampled sinusoid: a^2 sin^4(pi f m tau0) / (m sin(pi f tau0))^2
    at tau = m tau0 (``m`` the factors of the taus)."""
    co = fit["coefficients"]
    c = {t: (getattr(co, t).value if getattr(co, t).resolved else 0.0) for t in fit["terms"]}
    s2 = (3 * c.get("Q", 0) ** 2 / tau ** 2 + c.get("N", 0) ** 2 / tau
          + B_FACTOR ** 2 * c.get("B", 0) ** 2 + c.get("K", 0) ** 2 * tau / 3
          + c.get("R", 0) ** 2 * tau ** 2 / 2)
    for g in getattr(co, "gm", ()):  # a first-order Gauss-Markov term the fit carries
        if g.sigma.resolved:
            x = tau / g.tau_c_s
            s2 = s2 + g.sigma.value ** 2 * (2 * x - 3 + 4 * np.exp(-x) - np.exp(-2 * x)) / x ** 2
    if m is not None:
        mm = np.asarray(m, float)
        tau0 = float(tau[0] / mm[0])
        for tone in (fit.get("tones") or {}).get("terms", []):
            f, a = tone["freq_hz"], tone["amp_si"]
            s2 = s2 + a * a * np.sin(np.pi * f * mm * tau0) ** 4 / (mm * np.sin(np.pi * f * tau0)) ** 2
    return np.sqrt(s2)


def informative_taus(edf: np.ndarray) -> np.ndarray:
    """Taus whose 95 % chi-square band is informative: hi95 / lo95 = sqrt(chi2_0.975(nu) /
    chi2_0.025(nu)) <= 2 (nu >= 16.95), from the EDF (scipy's chi-square, not rigctl's)."""
    from scipy.stats import chi2

    nu = np.asarray(edf, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(chi2.ppf(0.975, nu) / chi2.ppf(0.025, nu)) <= 2.0


def check_axis(r: dict) -> dict:
    sys.path.insert(0, str(ROOT / "tests"))
    from allan_independent import bound_ceiling

    from rigctl.solvers import allan_fit as F

    sensor, unit = r["sensor"], r["_unit"]
    tau = np.asarray(r["tau_s"], float)
    dev = np.asarray(r[f"adev_{r['_si']}"], float)
    fac = float(np.asarray(r[f"adev_{unit}"])[0] / dev[0])
    informative = informative_taus(r["edf"])
    sel = informative if informative.any() else np.ones(tau.size, bool)
    # what a bound may reach: the curve where the fit needs its own model error (it holds its
    # terms to the measured curve there), else what the curve permits at 95 %, its upper
    # chi-square band simultaneous over these taus (tests/allan_independent.bound_ceiling)
    lim = limits_from_curve(tau[sel], bound_ceiling(dev[sel], np.asarray(r["edf"], float)[sel],
                                                    r["fit"]["check"]["model_error_rel"],
                                                    F.MODEL_ERROR_HOLD))
    # Done-when item 1's literal wording: the measured point, min sigma / 0.664 etc., over the
    # informative taus (no allowance for the curve's own chi-square scatter)
    lim_pt = limits_from_curve(tau[sel], dev[sel])
    lim_all = limits_from_curve(tau, dev)
    over, over_pt, over_all = [], [], []
    pt_ratio: dict[str, float] = {}  # bound / point limit, where above it
    for t in r["fit"]["terms"]:
        c = getattr(r["fit"]["coefficients"], t)
        if not c.resolved and c.upper95 > lim[t] * (1 + 1e-9):
            over.append(t)
        if not c.resolved and c.upper95 > lim_pt[t] * (1 + 1e-9):
            over_pt.append(t)
            pt_ratio[t] = float(c.upper95 / lim_pt[t])
        if not c.resolved and c.upper95 > lim_all[t] * (1 + 1e-9):
            over_all.append(t)
    lo = np.asarray(r[f"lo95_{unit}"]) / fac
    hi = np.asarray(r[f"hi95_{unit}"]) / fac
    fit = total_sigma(tau, r["fit"], sensor, r["m"])
    outside = informative & ((fit < lo) | (fit > hi))
    check = r["fit"]["check"]
    named = np.zeros(tau.size, bool)
    for o in ((check.get("outside") or []) + (check.get("outside_small") or [])
              + (check.get("outside_past_prefix") or [])):
        named |= (tau >= o["tau_from_s"] * (1 - 1e-12)) & (tau <= o["tau_to_s"] * (1 + 1e-12))
    unnamed = outside & ~named
    return {"over": over, "over_pt": over_pt, "pt_ratio": pt_ratio, "over_all": over_all, "n_inf": int(informative.sum()), "n_out": int(outside.sum()),
            "n_unnamed": int(unnamed.sum()),
            "unnamed_taus": [float(x) for x in tau[unnamed][:6]],
            "worst_unnamed": float(np.max(np.abs(np.log(dev[unnamed] / fit[unnamed]))))
            if unnamed.any() else 0.0,
            "check_ok": bool(check["ok"]), "n_named": int((outside & named).sum())}


def agree(ra: dict, rb: dict) -> list[str]:
    """Terms on which two tau sets disagree beyond their 95 % intervals / bounds."""
    bad = []
    for t in ra["fit"]["terms"]:
        a, b = getattr(ra["fit"]["coefficients"], t), getattr(rb["fit"]["coefficients"], t)
        if a.resolved and b.resolved:
            (la, ha), (lb, hb) = a.ci95, b.ci95
            if la > hb or lb > ha:
                bad.append(t)
        elif a.resolved != b.resolved:
            s, u = (a, b) if a.resolved else (b, a)
            if s.ci95[0] > u.upper95:
                bad.append(t)
    return bad


def term_text(fit: dict, t: str) -> str:
    from rigctl.solvers.noise_coefficients import in_field_units

    c = in_field_units(fit["coefficients"], t)[0]
    return f"{c.value:.3g}" if c.resolved else f"<{c.upper95:.3g}"


# ------------------------------------------------------------------ main
def analyse(name: str, rec: Path, info: dict, totals: dict,
            tau_sets: tuple = TAU_SETS) -> None:
    from rigctl.analysis import allan as AA
    from rigctl.solvers import allan_fit as F

    res = {}
    for taus in tau_sets:
        t = time.perf_counter()
        res[taus] = AA.compute(str(rec), info["axes"], taus)
        totals["analysis_s"] += time.perf_counter() - t
    first = res[tau_sets[-1]]
    g = first["gaps"]
    print(f"\n== {name}: {first['n_samples']} samples at {first['sample_rate_hz']:g} Hz "
          f"({first['n_samples'] / first['sample_rate_hz'] / 3600:.2f} h); gaps: "
          f"{g['count']} ({g['missing_samples']} samples, skipped){'; ' + info['datasheet'] if info.get('datasheet') else ''}")
    print(f"{'axis':>4} {'taus':>6} {'N':>10} {'B':>10} {'K':>10} {'B_floor':>9} "
          f"{'over_lim':>8} {'over_pt':>7} {'inf':>4} {'out':>4} {'named':>5} {'unnamed':>7} {'check':>5} "
          f"{'oct~all':>8}")
    for a in info["axes"]:
        sensor = first["axes"][a]["sensor"]
        ra, rb = res["octave"]["axes"][a], res["all"]["axes"][a]
        for tone in (ra.get("tones") or {}).get("tones", []):  # found before the fit
            unit = ra["_unit"]
            totals["tones"].append(f"{name}:{a}:{tone['freq_hz']:.2f}Hz:"
                                   f"{tone[f'amp_{unit}']:.3g}{unit}")
        bad = agree(ra, rb)
        both_ok = ra["fit"]["check"]["ok"] and rb["fit"]["check"]["ok"]
        totals["pairs"] += 1
        totals["disagree"] += bool(bad)
        totals["disagree_checks_ok"] += bool(bad) and both_ok
        if bad:
            totals["disagree_where"].append(
                f"{name}:{a}:{''.join(bad)}({'checks ok' if both_ok else 'a check failed'})")
        for taus in tau_sets:
            r = res[taus]["axes"][a]
            c = check_axis(r)
            totals["fits"] += 1
            totals["over_limit"] += bool(c["over"])
            totals["over_all_taus"] += bool(c["over_all"])
            totals["over_point"] += bool(c["over_pt"])
            for term in c["over_pt"]:
                totals["over_point_terms"][term] = totals["over_point_terms"].get(term, 0) + 1
                totals["over_point_max_ratio"][term] = round(max(
                    totals["over_point_max_ratio"].get(term, 0.0), c["pt_ratio"][term]), 3)
            if c["over_pt"]:
                totals["over_point_where"].append(f"{name.split(' (')[0]}:{a}:{taus}:" + ",".join(
                    f"{t}x{c['pt_ratio'][t]:.2f}" for t in c["over_pt"]))
            for term in c["over_all"]:
                totals["over_all_terms"][term] = totals["over_all_terms"].get(term, 0) + 1
            if c["over_all"]:
                totals["over_all_where"].append(f"{name}:{a}:{taus}:{''.join(c['over_all'])}")
            if c["over"]:
                totals["over_where"].append(f"{name}:{a}:{taus}:{''.join(c['over'])}")
            if r["fit"].get("gm_term"):
                totals["gm_terms"].append(f"{name}:{a}:{taus}:Tc{r['fit']['gm_term']['tc_s']:.3g}s")
            totals["outside"] += c["n_out"]
            totals["informative"] += c["n_inf"]
            totals["unnamed"] += c["n_unnamed"]
            totals["fits_with_unnamed"] += bool(c["n_unnamed"])
            if c["n_unnamed"]:
                totals["unnamed_where"].append(
                    f"{name}:{a}:{taus}:{c['n_unnamed']}@{c['unnamed_taus'][0]:.3g}s"
                    f"(x{math.exp(c['worst_unnamed']):.2f})")
            totals["check_failed"] += not c["check_ok"]
            dev = np.asarray(r[f"adev_{r['_unit']}"])
            bu, bf = F.FIELD_UNITS[sensor]["B"]
            inf = informative_taus(r["edf"])
            # min sigma / 0.664 over the informative taus, field units
            floor = float(dev[inf].min() if inf.any() else dev.min()) / B_FACTOR
            print(f"{a:>4} {str(taus):>6} {term_text(r['fit'], 'N'):>10} "
                  f"{term_text(r['fit'], 'B'):>10} {term_text(r['fit'], 'K'):>10} "
                  f"{floor:9.3g} {','.join(c['over']) or '-':>8} {','.join(c['over_pt']) or '-':>7} {c['n_inf']:4d} {c['n_out']:4d} "
                  f"{c['n_named']:5d} {c['n_unnamed']:7d} {'ok' if c['check_ok'] else 'FAIL':>5} "
                  f"{('-' if not bad else ','.join(bad)) if taus == 'octave' else '':>8}",
                  flush=True)
    units = {s: (F.FIELD_UNITS[s]["N"][0], F.FIELD_UNITS[s]["B"][0], F.FIELD_UNITS[s]["K"][0])
             for s in ("gyro", "accel")}
    print("   units: gyro N, B, K in " + ", ".join(units["gyro"]) + "; accel in "
          + ", ".join(units["accel"]) + "; B_floor = min sigma / 0.664 (B's unit)")


def run_cases(wanted: list[str], hours: float, sets: tuple, keep: str | None = None,
              warmup_s: float = WARMUP_S) -> dict:
    """Write and analyse every case of ``wanted``; the counts of the three checks."""
    totals = {"fits": 0, "over_limit": 0, "over_where": [], "over_all_taus": 0,
              "over_point": 0, "over_point_where": [], "over_point_terms": {},
              "over_point_max_ratio": {},
              "over_all_where": [], "over_all_terms": {}, "informative": 0, "outside": 0,
              "unnamed": 0, "fits_with_unnamed": 0, "unnamed_where": [], "check_failed": 0,
              "pairs": 0, "disagree": 0, "disagree_checks_ok": 0, "disagree_where": [],
              "tones": [], "analysis_s": 0.0, "generate_s": 0.0, "gm_terms": []}
    with tempfile.TemporaryDirectory(dir="/tmp") as d:
        tmp = Path(keep or d)
        tmp.mkdir(parents=True, exist_ok=True)
        for case in wanted:
            if case == "real":
                for name, rec, info in real_recordings(tmp):
                    analyse(name, rec, info, totals, sets)
                continue
            rec = tmp / f"{case}_{hours:g}h_warmup{warmup_s:g}s.h5"
            t = time.perf_counter()
            if not rec.exists():
                info = emulated_recording(case, rec, hours, warmup_s=warmup_s)
            else:
                info = {"axes": ["gx", "gy", "gz", "ax", "ay", "az"]}
            totals["generate_s"] += time.perf_counter() - t
            analyse(f"{case} (emulated, {hours:g} h"
                    f"{f', after {warmup_s:g} s warm-up' if case != 'default' else ''})",
                    rec, info, totals, sets)
    return totals


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=12.0, help="emulated capture length, h")
    ap.add_argument("--cases", default="all",
                    help="comma-separated: default, profile names, real (default: all)")
    ap.add_argument("--keep", metavar="DIR", help="write the recordings here and keep them")
    ap.add_argument("--warmup-s", type=float, default=WARMUP_S,
                    help="profiles: capture from this long after power-on, s (default 900, "
                         "procedures/warmup.yaml's 15 min; 0: from power-on)")
    ap.add_argument("--taus", default="octave,all,95",
                    help="tau sets (octave and all always; default octave,all,95)")
    a = ap.parse_args()
    from rigctl.sim.profiles import profile_names

    emulated = ["default"] + [p for p in profile_names() if p != "random"]
    wanted = emulated + ["real"] if a.cases == "all" else a.cases.split(",")
    sets = tuple(dict.fromkeys(["octave", "all"] + [int(t) if t.isdigit() else t
                                                    for t in a.taus.split(",")]))
    load0 = _load()
    t0 = time.perf_counter()
    totals = run_cases(wanted, a.hours, sets, a.keep, a.warmup_s)
    wall = time.perf_counter() - t0
    print(f"\n{totals['fits']} fits (case x axis x tau set {sets}): bounds above the curve's "
          f"limit: {totals['over_limit']} (the literal point limit, min sigma / 0.664 etc. over the "
          f"informative taus: {totals['over_point']} fits, per term {totals['over_point_terms']}, "
          f"largest bound / limit {totals['over_point_max_ratio']}; "
          f"the limit over every tau, incl. EDF < 16.95: "
          f"{totals['over_all_taus']} fits, per term {totals['over_all_terms']}); fitted total outside the 95 % band at "
          f"{totals['outside']} of {totals['informative']} informative taus, of them not named "
          f"by the self-check: {totals['unnamed']} (in {totals['fits_with_unnamed']} fits); "
          f"self-check failed (warning): {totals['check_failed']}; octave vs all disagree "
          f"beyond their intervals: {totals['disagree']} of {totals['pairs']} axes "
          f"({totals['disagree_checks_ok']} of them with both self-checks passed). "
          f"{wall:.0f} s (load {load0} -> {_load()})")
    print(f"Gauss-Markov terms in the fit: {len(totals['gm_terms'])} of {totals['fits']} fits")
    for k in ("over_where", "over_point_where", "over_all_where", "unnamed_where", "disagree_where", "tones",
              "gm_terms"):
        if totals[k]:
            print(f"{k}: {'; '.join(totals[k][:30 if k != 'over_point_where' else 200])}")
    print(json.dumps({"hours_emulated": a.hours, "warmup_s": a.warmup_s, "cases": wanted,
                      "fits": totals["fits"],
                      "bounds_above_curve_limit": totals["over_limit"],
                      "bounds_above_point_limit_informative_taus": totals["over_point"],
                      "bounds_above_point_limit_per_term": totals["over_point_terms"],
                      "bounds_above_point_limit_max_ratio": totals["over_point_max_ratio"],
                      "bounds_above_limit_over_every_tau": totals["over_all_taus"],
                      "bounds_above_limit_over_every_tau_per_term": totals["over_all_terms"],
                      "informative_taus": totals["informative"],
                      "taus_outside_band": totals["outside"],
                      "taus_outside_band_not_named": totals["unnamed"],
                      "fits_with_unnamed_taus": totals["fits_with_unnamed"],
                      "self_check_failed_fits": totals["check_failed"],
                      "octave_vs_all_disagree_axes": totals["disagree"],
                      "octave_vs_all_axes": totals["pairs"],
                      "octave_vs_all_disagree_with_checks_ok": totals["disagree_checks_ok"],
                      "axes_with_tones": len({w.rsplit(":", 2)[0] for w in totals["tones"]}),
                      "fits_with_gauss_markov_term": len(totals["gm_terms"]),
                      "generate_s": round(totals["generate_s"], 1),
                      "analysis_s": round(totals["analysis_s"], 1), "wall_s": round(wall, 1),
                      "load_avg_start": load0, "load_avg_end": _load()}))


if __name__ == "__main__":
    sys.exit(main())
