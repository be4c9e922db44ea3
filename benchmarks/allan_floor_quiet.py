"""B near the floor on the FAIL-total rows of benchmarks/allan_heldout.py, read without rigctl's
fit (docs/allan.md, "The five FAIL-total rows read independently").

    python benchmarks/allan_floor_quiet.py [--keep DIR] [--sim N]

For each row (ADIS16405 ax, ay default; ADIS16405 gx octave; OCXO default and octave), with
the curve read by allan_heldout's numpy functions (overlapping ADEV, exact EDFs, bands, floor
taus) and rigctl's JSON used only for its tau grid, its coefficients (to compare) and the quiet
stretch its stationarity test names:

1. an N + B + K (+ Q for the OCXO) weighted least-squares fit written here (sigma^2, var =
   2 sigma^4 / EDF with the model's sigma^2, iterated; non-negative; taus informative and past
   the tone / filter region: >= 5 s for the ADIS16405 accelerometers, >= 0.05 s for its gyro,
   >= 1 s for the OCXO) on the whole record, on the quiet stretch, and on the record without
   its loudest window; B's 95 % interval from the fit's covariance (correlation across taus
   neglected: too narrow) and from the spread of the same fit in the stretch's windows
   (Student t);
2. rigctl itself on the quiet stretch (`rigctl import` of that stretch, `rigctl allan`), judged
   with allan_heldout's own `judge`;
3. the best the IEEE 952 model can do at the floor's taus within rigctl's own limits: N read
   at the short taus (ADIS16405: the median of sigma sqrt(tau) at 0.02-0.2 s; OCXO: Q and N
   from 1-10 s), rigctl's tones, K <= rigctl's K limit, B free: the smallest worst depth
   (|total - curve| in half-widths of the 95 % band on the side missed) over the floor taus,
   and what that total misses over all informative taus, beside rigctl's;
4. at each floor tau rigctl's total misses: the depth, the curve's level and slope, both EDFs,
   and whether rigctl's self-check names the tau;
5. with --sim N: how often item 2 (the total in the band at every floor tau, or within 10 %)
   fails for N simulated stationary records with the OCXO's and the ADIS16405's terms, with
   the true total (the ensemble's mean Allan variance) and with the fit of 1. on each record,
   on the pointwise band and on allan_heldout's family-wise band (and Sidak over the count of
   floor taus), with Clopper-Pearson 95 % upper bounds (--sim-adis N: records per ADIS16405
   case, default N // 3; --sim-cases: some cases only; each record's curve kept in --keep,
   --sim-judge judges the kept records without drawing);
   with --sim-rigctl N: rigctl itself on N simulated stationary OCXO-like records (its
   verdicts by allan_heldout's judge, and how often B's 95 % interval holds the simulated B);
   --sim-rigctl-adis N: the same on N ADIS16405 ax-like records (1e6 samples each).

Last line: one JSON object (counts, seconds).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.optimize import nnls
from scipy.stats import beta as beta_dist
from scipy.stats import chi2
from scipy.stats import t as student

sys.path.insert(0, str(Path(__file__).resolve().parent))
import allan_heldout as H  # noqa: E402  (the numpy read of the curve; no rigctl at import)

BF = H.B_FACTOR
D2R = math.pi / 180
ROWS = [("ADIS16405", "ax", "default"), ("ADIS16405", "ay", "default"), ("ADIS16405", "gx", "octave"),
        ("OCXO", "gx", "default"), ("OCXO", "gx", "octave")]
TAU_LO = {("ADIS16405", "ax"): 5.0, ("ADIS16405", "ay"): 5.0, ("ADIS16405", "gx"): 0.05,
          ("OCXO", "gx"): 1.0}
TERMS = {"ADIS16405": ["N", "B", "K"], "OCXO": ["Q", "N", "B", "K"]}
ADIS_COLS = ["--rate", "100", "--columns", "gyr_x=0,gyr_y=1,gyr_z=2,acc_x=3,acc_y=4,acc_z=5",
             "--units", "gyr=counts:0.05 deg/s,acc=counts:0.00333 g"]
OCXO_COLS = ["--columns", "gyr_x=0", "--units", "gyr=counts:1e-07 rad/s", "--rate", "1"]


def design(tau: np.ndarray, terms: list[str]) -> np.ndarray:
    cols = {"Q": 3 / tau ** 2, "N": 1 / tau, "B": np.full_like(tau, BF ** 2), "K": tau / 3}
    return np.column_stack([cols[k] for k in terms])


def wls(tau, dev, edf, sel, terms, iters=30):
    """Non-negative weighted least squares on sigma^2 (module docstring, 1.): coefficients (SI),
    s.d. of the squared coefficients, chi-square, dof."""
    A, y, nu = design(tau[sel], terms), dev[sel] ** 2, edf[sel]
    s2 = y.copy()
    for _ in range(iters):
        w = np.sqrt(nu / 2) / s2
        c, _ = nnls(A * w[:, None], y * w)
        s2n = np.maximum(A @ c, 1e-300)
        if np.allclose(s2n, s2, rtol=1e-10):
            break
        s2 = s2n
    act = c > 0
    sd = np.full(len(terms), np.nan)
    if act.any():
        Aw = (A * w[:, None])[:, act]
        sd[act] = np.sqrt(np.diag(np.linalg.inv(Aw.T @ Aw)))
    chi = float((((y - A @ c) * w) ** 2).sum())
    return dict(zip(terms, np.sqrt(c))), dict(zip(terms, sd)), chi, int(sel.sum() - act.sum())


def total(coef: dict, tau: np.ndarray) -> np.ndarray:
    return np.sqrt(sum(design(np.atleast_1d(tau), [k])[:, 0] * v ** 2 for k, v in coef.items()))


def depth(dev, lo, hi, tot):
    """|total - curve| in half-widths of the band on the side the total lies."""
    return np.where(tot < dev, (dev - tot) / (dev - lo), (tot - dev) / (hi - dev))


def missed(c, tot, mask):
    """allan_heldout's rule: outside the band and more than 10 % off the curve."""
    return mask & (((tot < c["lo"]) & (c["dev"] > 1.1 * tot)) | ((tot > c["hi"]) & (c["dev"] < 0.9 * tot)))


def informative(c):
    return c["hi"] / np.maximum(c["lo"], 1e-300) <= 2


def floor_rows(c, tot):
    ft = np.flatnonzero(c["floor_taus"])
    dp = depth(c["dev"][ft], c["lo"][ft], c["hi"][ft], tot[ft])
    ms = missed(c, tot, c["floor_taus"])[ft]
    return [{"tau_s": float(c["tau"][k]), "total_over_curve": float(tot[k] / c["dev"][k]),
             "band": [float(c["lo"][k] / c["dev"][k]), float(c["hi"][k] / c["dev"][k])],
             "depth": float(d), "missed": bool(m)} for k, d, m in zip(ft, dp, ms)]


def read(y, t0, ms, tau_lo, terms):
    L = max(len(p) for p in y) if isinstance(y, list) else len(y)
    ms = ms[2 * ms < L]
    c = H.read_curve(y, t0, ms)
    sel = informative(c) & (c["tau"] >= tau_lo * (1 - 1e-9))
    coef, sd, chi, dof = wls(c["tau"], c["dev"], c["edf"], sel, terms)
    return c, coef, sd, chi, dof


def b_ci_diag(coef, sd):
    b2 = coef["B"] ** 2
    return [math.sqrt(max(b2 - 1.96 * sd["B"], 0.0)), math.sqrt(b2 + 1.96 * sd["B"])]


def rigctl_total(r, tau, t0):
    tones = r["fit"].get("tones", {}).get("terms", [])
    return np.array([H.total(r["fit"]["coefficients"], tones, float(x), t0) for x in tau])


def tone_var(tones, tau, t0):
    m = tau / t0
    return sum(t["amp_si"] ** 2 * np.sin(np.pi * t["freq_hz"] * tau) ** 4
               / (m * np.sin(np.pi * t["freq_hz"] * t0)) ** 2 for t in tones)


def k_limit(r):
    kt = r["fit"]["terms"]["K"]
    for pre in ("held_limit_", "curve_limit_"):
        v = [x for k, x in kt.items() if k.startswith(pre) and "/h" not in k and "tau" not in k]
        if v:
            return float(v[0])
    return math.inf


def best_at_floor(c, r, t0, cap):
    """3. of the module docstring."""
    tau, dev, ok = c["tau"], c["dev"], informative(c)
    if cap == "ADIS16405":
        sh = ok & (tau >= 0.02) & (tau <= 0.2)
        N, Q = float(np.median(dev[sh] * np.sqrt(tau[sh]))), 0.0
    else:
        sh = ok & (tau <= 10)
        q, _ = nnls(design(tau[sh], ["Q", "N"]) / dev[sh, None] ** 2, np.ones(sh.sum()))
        Q, N = np.sqrt(q)
    tv = np.array([tone_var(r["fit"].get("tones", {}).get("terms", []), x, t0) for x in tau])
    klim = min(k_limit(r), float(np.min(dev[ok] * np.sqrt(3 / tau[ok]))))
    ft = np.flatnonzero(c["floor_taus"])
    base = 3 * Q ** 2 / tau[ft] ** 2 + N ** 2 / tau[ft] + tv[ft]
    Bs = np.linspace(0, 1.2 * c["floor"] / BF, 601)
    best = (math.inf, 0.0, 0.0)
    for K in np.linspace(0, klim, 301):
        T = np.sqrt(base[None, :] + (BF * Bs[:, None]) ** 2 + K ** 2 * tau[ft][None, :] / 3)
        dp = depth(dev[ft][None, :], c["lo"][ft][None, :], c["hi"][ft][None, :], T)
        ms = ((T < c["lo"][ft]) & (dev[ft] > 1.1 * T)) | ((T > c["hi"][ft]) & (dev[ft] < 0.9 * T))
        w = dp.max(axis=1) + 100 * ms.sum(axis=1)
        i = int(np.argmin(w))
        if w[i] < best[0]:
            best = (float(w[i]), float(Bs[i]), float(K))
    T = np.sqrt(3 * Q ** 2 / tau ** 2 + N ** 2 / tau + tv + (BF * best[1]) ** 2 + best[2] ** 2 * tau / 3)
    R = rigctl_total(r, tau, t0)
    return {"N_short": N, "Q": Q, "K_limit": klim, "B": best[1], "B_over_limit": best[1] / (c["floor"] / BF),
            "K": best[2], "worst_depth_floor": best[0],
            "missed_all_informative": int(missed(c, T, ok).sum()),
            "rigctl_missed_all_informative": int(missed(c, R, ok).sum()), "n_informative": int(ok.sum())}


def load(keep: Path) -> dict:
    d = H.DATA
    g = np.loadtxt(d / "adis16405-static" / "gyro_counts.txt.gz", dtype=np.int64)
    a = np.loadtxt(d / "adis16405-static" / "accel_counts.txt.gz", dtype=np.int64)
    txt = keep / "adis16405.txt"
    if not txt.is_file():
        np.savetxt(txt, np.column_stack([g, a]), fmt="%d")
    import gzip
    otxt = keep / "ocxo_frequency.txt"
    if not otxt.is_file():
        otxt.write_bytes(gzip.decompress((d / "ocxo-frequency-stable32" / "ocxo_frequency.txt.gz").read_bytes()))
    o = np.loadtxt(otxt) * 1e-7
    return {("ADIS16405", "ax"): (a[:, 0] * 0.00333 * 9.80665, 0.01, txt, ADIS_COLS),
            ("ADIS16405", "ay"): (a[:, 1] * 0.00333 * 9.80665, 0.01, txt, ADIS_COLS),
            ("ADIS16405", "gx"): (g[:, 0] * 0.05 * D2R, 0.01, txt, ADIS_COLS),
            ("OCXO", "gx"): (o, 1.0, otxt, OCXO_COLS)}


def rigctl_json(keep: Path, txt: Path, cols: list[str], rows: tuple[int, int] | None, taus: str, ax: str) -> dict:
    """`rigctl import` of the file (or of its rows a:b) and `rigctl allan --json`, cached in keep."""
    tag = f"{txt.stem}_{rows[0]}_{rows[1]}" if rows else txt.stem
    js = keep / f"{tag}_{taus}.json"
    if not js.is_file():
        src = txt
        if rows:
            src = keep / f"{tag}.txt"
            # the data rows (the OCXO file's '#' header lines are not samples: slicing the
            # text's lines shifted its stretch by their count)
            lines = [ln for ln in txt.read_text().splitlines()
                     if ln.strip() and not ln.lstrip().startswith(("#", "%"))]
            src.write_text("\n".join(lines[rows[0]:rows[1]]) + "\n")
        rec = keep / f"{tag}.h5"
        if not rec.is_file():
            H.rigctl("import", str(src), "-o", str(rec), "--force", *cols)
        H.rigctl("allan", str(rec), "--db", "none", "--json", str(js), *(["--taus", "octave"] if taus == "octave" else []))
    return json.loads(js.read_text())["axes"][ax]


def analyse_row(data, keep, cap, ax, taus) -> dict:
    y, t0, txt, cols = data[(cap, ax)]
    r = rigctl_json(keep, txt, cols, None, taus, ax)
    ms = np.asarray(r["m"], int)
    terms, tau_lo = TERMS[cap], TAU_LO[(cap, ax)]
    c, coef, sd, chi, dof = read(y, t0, ms, tau_lo, terms)
    R = rigctl_total(r, c["tau"], t0)
    b = r["fit"]["coefficients"]["B"]
    named = [(o["tau_from_s"], o["tau_to_s"]) for o in r["fit"]["check"]["outside"]]
    slope = np.gradient(np.log(c["dev"]), np.log(c["tau"]))
    redf = np.asarray(r["edf"], float)
    miss_detail = []
    for k in np.flatnonzero(missed(c, R, c["floor_taus"])):
        miss_detail.append({"tau_s": float(c["tau"][k]), "total_over_curve": float(R[k] / c["dev"][k]),
                            "band": [float(c["lo"][k] / c["dev"][k]), float(c["hi"][k] / c["dev"][k])],
                            "depth": float(depth(c["dev"][k], c["lo"][k], c["hi"][k], R[k])),
                            "curve_over_floor": float(c["dev"][k] / c["floor"]), "slope": float(slope[k]),
                            "edf_script": float(c["edf"][k]), "edf_rigctl": float(redf[k]),
                            "named_by_self_check": any(a - 1e-9 <= c["tau"][k] <= bb + 1e-9 for a, bb in named)})
    out = {"row": f"{cap} {ax} {taus}",
           "whole": {"floor": c["floor"], "tau_floor_s": c["tau_floor"], "B_limit": c["floor"] / BF,
                     "rigctl_B": b.get("value"), "rigctl_B_ci95": b.get("ci95"),
                     "rigctl_floor_taus": floor_rows(c, R), "rigctl_missed": miss_detail,
                     "np_coef": coef, "np_B_ci95_diag": b_ci_diag(coef, sd), "np_chi2_dof": [chi, dof],
                     "np_floor_taus": floor_rows(c, total(coef, c["tau"])),
                     "best_at_floor": best_at_floor(c, r, t0, cap)}}
    st = [o["stationarity"] for o in r["fit"]["check"]["outside"] if o.get("cause") == "nonstationary"]
    if not st:
        return out
    s = st[0]
    a, bq = s["quiet_samples"]
    yq = np.asarray(y)[a:bq]
    cq, cfq, sdq, chq, dfq = read(yq, t0, ms, tau_lo, terms)
    ws = int(round(s["window_s"] / t0))
    bw = np.array([read(v, t0, ms, tau_lo, terms)[1]["B"] for v in np.array_split(yq, max(2, round(len(yq) / ws)))])
    half = float(student.ppf(0.975, len(bw) - 1) * bw.std(ddof=1) / math.sqrt(len(bw)))
    rq = rigctl_json(keep, txt, cols, (a, bq), taus, ax)
    cq_r = H.read_curve(yq, t0, np.asarray(rq["m"], int))
    jq = H.judge(rq, cq_r, t0)
    bqr = rq["fit"]["coefficients"]["B"]
    lw = int(np.argmax(s["ratio_to_median"]))
    e = np.linspace(0, len(y), s["windows"] + 1).round().astype(int)
    parts = [p for p in (np.asarray(y)[:e[lw]], np.asarray(y)[e[lw + 1]:]) if len(p)]
    cx, cfx, sdx, _, _ = read(parts, t0, ms, tau_lo, terms)
    out["quiet"] = {"samples": [a, bq], "bump_tau_s": s["tau_s"], "bartlett_p": s["p_value"],
                    "floor": cq["floor"], "tau_floor_s": cq["tau_floor"], "shows_floor": cq["shows_floor"],
                    "B_limit": cq["floor"] / BF, "np_coef": cfq, "np_B_ci95_diag": b_ci_diag(cfq, sdq),
                    "np_B_windows": bw.tolist(), "np_B_ci95_windows": [cfq["B"] - half, cfq["B"] + half],
                    "np_chi2_dof": [chq, dfq], "np_floor_taus": floor_rows(cq, total(cfq, cq["tau"])),
                    "rigctl_whole_total_on_quiet_curve": floor_rows(cq, rigctl_total(r, cq["tau"], t0)),
                    "rigctl_quiet_verdict": jq["verdict"], "rigctl_quiet_B": bqr.get("value"),
                    "rigctl_quiet_B_ci95": bqr.get("ci95"), "rigctl_quiet_B_over_limit": jq["b_over_limit"],
                    "rigctl_quiet_floor_taus": floor_rows(cq_r, rigctl_total(rq, cq_r["tau"], t0)),
                    "best_at_floor": best_at_floor(cq_r, rq, t0, cap)}
    out["without_loudest"] = {"window": [int(e[lw]), int(e[lw + 1])], "floor": cx["floor"],
                              "tau_floor_s": cx["tau_floor"], "np_coef": cfx, "np_B_ci95_diag": b_ci_diag(cfx, sdx),
                              "np_floor_taus": floor_rows(cx, total(cfx, cx["tau"]))}
    return out


# ------------------------------------------------------------------ 5. simulation
def _flicker(rng, n, tau0):
    f = np.fft.rfftfreq(2 * n, tau0)
    a = np.zeros_like(f)
    a[1:] = f[1:] ** -0.5
    return np.fft.irfft((rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) * a)[:n]


def simulate(name, n, tau0, ms, N, B, K, Q, tau_lo, terms, nsim, seed=15, keep=None, judge_only=False) -> dict:
    """Item 2 on nsim simulated stationary records (5. of the module docstring): how often the
    true total (the ensemble's mean Allan variance) and the numpy fit's total miss a floor tau,
    by the pointwise rule (allan_heldout's `FAIL-total`) and by the family-wise one
    (allan_heldout.familywise_band, under the total judged: the simulated terms for the true
    total, the fit's for the fit); beside them Sidak over the count of floor taus (as if
    independent). Record i is drawn from its own generator (seed, i); with ``keep`` each
    record's curve and fit are kept there and reused (``judge_only``: judge the records kept,
    none drawn), so a run cut short can be judged on the records it drew."""
    rng = np.random.default_rng(seed)
    f = _flicker(rng, n, tau0)
    c0 = H.read_curve(f, tau0, ms)
    scale = BF / float(np.median(c0["dev"][informative(c0) & (ms > 10)]))
    store = Path(keep) / ("sim_" + name.replace(" ", "_")) if keep else None
    if store:
        store.mkdir(parents=True, exist_ok=True)
    if judge_only and store:
        nsim = 0
        while (store / f"r{nsim}.npz").is_file():
            nsim += 1
    curves, devs = [], []
    for i in range(nsim):
        fn = store / f"r{i}.npz" if store else None
        if fn is not None and fn.is_file():
            z = np.load(fn)
            c = {k: z[k] for k in ("tau", "dev", "lo", "hi", "edf", "floor_taus")}
            c["lengths"], c["shows_floor"] = [int(x) for x in z["lengths"]], bool(z["shows_floor"])
            coef = dict(zip(terms, z["coef"])) if c["shows_floor"] else None
        else:
            rng = np.random.default_rng([seed, i])
            y = N / math.sqrt(tau0) * rng.standard_normal(n) + B * scale * _flicker(rng, n, tau0)
            y += np.cumsum(K * math.sqrt(tau0) * rng.standard_normal(n))
            if Q:  # white phase noise of s.d. Q: sigma^2 = 3 Q^2 / tau^2
                y += np.diff(Q * rng.standard_normal(n + 1)) / tau0
            c = H.read_curve(y, tau0, ms)
            coef = (wls(c["tau"], c["dev"], c["edf"], informative(c) & (c["tau"] >= tau_lo), terms)[0]
                    if c["shows_floor"] else None)
            if fn is not None:
                np.savez(fn, **{k: c[k] for k in ("tau", "dev", "lo", "hi", "edf", "floor_taus")},
                         lengths=np.asarray(c["lengths"]), shows_floor=c["shows_floor"],
                         coef=np.array([coef[t] for t in terms]) if coef else np.zeros(len(terms)))
        devs.append(c["dev"])
        if c["shows_floor"]:
            curves.append((c, coef))
    truth = np.sqrt((np.array(devs) ** 2).mean(axis=0))
    true_s2 = {"Q": Q ** 2, "N": N ** 2, "B": (BF * B) ** 2, "K": K ** 2}
    res = {"case": name, "n": nsim, "shows_floor": len(curves), "n_floor_taus": [],
           "fw_level_per_tau_true": [], "fw_m_equiv_true": []}
    for key in ("true", "fit"):
        for rule in ("outside", "missed", "outside_fw", "missed_fw", "missed_sidak_n"):
            res[f"{key}_{rule}"] = 0
    for c, coef in curves:
        ft = np.flatnonzero(c["floor_taus"])
        res["n_floor_taus"].append(int(ft.size))
        d, lo, hi = c["dev"][ft], c["lo"][ft], c["hi"][ft]
        q_n = -math.expm1(math.log1p(-H.FW_ALPHA) / max(ft.size, 1))  # Sidak over the count
        nu = c["edf"][ft]
        lo_n, hi_n = d * np.sqrt(nu / chi2.ppf(1 - q_n / 2, nu)), d * np.sqrt(nu / chi2.ppf(q_n / 2, nu))
        for key, T, s2 in (("true", truth[ft], true_s2),
                           ("fit", total(coef, c["tau"][ft]),
                            {t: (BF ** 2 if t == "B" else 1.0) * v ** 2 for t, v in coef.items()})):
            fwb = H.familywise_band(c, ft, s2, tau0, c["lengths"])
            if key == "true":
                res["fw_level_per_tau_true"].append(fwb["q"])
                res["fw_m_equiv_true"].append(fwb["m_equiv"])
            res[f"{key}_outside"] += int(((T < lo) | (T > hi)).any())
            res[f"{key}_missed"] += int(H.item2_missed(d, lo, hi, T).any())
            res[f"{key}_outside_fw"] += int(((T < fwb["lo"]) | (T > fwb["hi"])).any())
            res[f"{key}_missed_fw"] += int(H.item2_missed(d, fwb["lo"], fwb["hi"], T).any())
            res[f"{key}_missed_sidak_n"] += int(H.item2_missed(d, lo_n, hi_n, T).any())
    for k in ("n_floor_taus", "fw_level_per_tau_true", "fw_m_equiv_true"):
        v = res.pop(k)
        res[k + "_range"] = [min(v), max(v)] if v else None
    nf = max(res["shows_floor"], 1)
    for k in [k for k in res if k.startswith(("true_", "fit_"))]:
        # the rate and its 95 % upper bound (Clopper-Pearson) among the records showing a floor
        x = res[k]
        res[k + "_rate"] = x / nf
        res[k + "_up95"] = float(beta_dist.ppf(0.95, x + 1, nf - x)) if x < nf else 1.0
    return res


def simulate_rigctl(keep: Path, nsim: int, seed: int = 2015) -> dict:
    """rigctl itself (`rigctl import` + `rigctl allan`, default and octave) on nsim simulated
    stationary OCXO-like records, judged with allan_heldout's judge: its verdicts, and whether B's
    95 % interval holds the simulated B."""
    rng = np.random.default_rng(seed)
    n, tau0, Bt, Kt, Qt = 19982, 1.0, 6.4e-12, 2.7e-13, 4.3e-11
    ms0 = np.unique(np.round(np.logspace(0, math.log10(n / 3), 95)).astype(int))
    c0 = H.read_curve(_flicker(rng, n, tau0), tau0, ms0)
    scale = BF / float(np.median(c0["dev"][informative(c0) & (ms0 > 10)]))
    out = {t: {"verdicts": {}, "verdicts_familywise": {}, "b_ci_holds_truth": 0, "b_over_truth": []}
           for t in ("default", "octave")}
    d = keep / "sim_rigctl"
    d.mkdir(exist_ok=True)
    for i in range(nsim):
        y = Bt * scale * _flicker(rng, n, tau0) + np.cumsum(Kt * math.sqrt(tau0) * rng.standard_normal(n))
        y += np.diff(Qt * rng.standard_normal(n + 1)) / tau0
        txt, rec = d / f"s{i}.txt", d / f"s{i}.h5"
        if not all((d / f"s{i}_{taus}.json").is_file() for taus in out):  # rigctl's JSON kept: reused
            np.savetxt(txt, y / 1e-7, fmt="%.9e")
            H.rigctl("import", str(txt), "-o", str(rec), "--force", *OCXO_COLS)
        for taus, o in out.items():
            js = d / f"s{i}_{taus}.json"
            if not js.is_file():
                H.rigctl("allan", str(rec), "--db", "none", "--json", str(js),
                         *(["--taus", "octave"] if taus == "octave" else []))
            r = json.loads(js.read_text())["axes"]["gx"]
            j = H.judge(r, H.read_curve(y, tau0, np.asarray(r["m"], int)), tau0)
            o["verdicts"][j["verdict"]] = o["verdicts"].get(j["verdict"], 0) + 1
            o["verdicts_familywise"][j["verdict_familywise"]] = o["verdicts_familywise"].get(j["verdict_familywise"], 0) + 1
            o["b_ci_holds_truth"] += int((j["b_lo95"] or 0.0) <= Bt <= j["b_hi95"])
            o["b_over_truth"].append((j["b"] or j["b_hi95"]) / Bt)
    for o in out.values():
        o["b_over_truth_median"] = float(np.median(o.pop("b_over_truth")))
    return {"case": "rigctl on OCXO-like records", "n": nsim, **out}


def simulate_rigctl_adis(keep: Path, nsim: int, seed: int = 405) -> dict:
    """As :func:`simulate_rigctl` for ADIS16405 ax-like records (white 4.3e-3 m/s/sqrt(s),
    B 3.5e-3 m/s^2, K 4.2e-4 m/s^2/sqrt(s); 1e6 samples at 100 Hz, no tones), default taus."""
    rng = np.random.default_rng(seed)
    n, tau0, Nt, Bt, Kt = 10 ** 6, 0.01, 4.3e-3, 3.5e-3, 4.2e-4
    ms0 = np.unique(np.round(np.logspace(0, math.log10(n / 3), 95)).astype(int))
    c0 = H.read_curve(_flicker(rng, n, tau0), tau0, ms0)
    scale = BF / float(np.median(c0["dev"][informative(c0) & (ms0 > 10)]))
    out = {"verdicts": {}, "verdicts_familywise": {}, "b_ci_holds_truth": 0, "check_ok": 0, "b_over_truth": []}
    d = keep / "sim_rigctl_adis"
    d.mkdir(exist_ok=True)
    for i in range(nsim):
        y = (Nt / math.sqrt(tau0) * rng.standard_normal(n) + Bt * scale * _flicker(rng, n, tau0)
             + np.cumsum(Kt * math.sqrt(tau0) * rng.standard_normal(n)))
        txt, rec, js = d / f"s{i}.txt", d / f"s{i}.h5", d / f"s{i}.json"
        if not js.is_file():  # rigctl's JSON kept in --keep: reused
            np.savetxt(txt, y / 9.80665, fmt="%.9e")
            H.rigctl("import", str(txt), "-o", str(rec), "--force", "--rate", "100", "--columns", "acc_x=0",
                     "--units", "acc=g")
            H.rigctl("allan", str(rec), "--db", "none", "--json", str(js))
        r = json.loads(js.read_text())["axes"]["ax"]
        j = H.judge(r, H.read_curve(y, tau0, np.asarray(r["m"], int)), tau0)
        out["verdicts"][j["verdict"]] = out["verdicts"].get(j["verdict"], 0) + 1
        out["verdicts_familywise"][j["verdict_familywise"]] = out["verdicts_familywise"].get(j["verdict_familywise"], 0) + 1
        out["b_ci_holds_truth"] += int((j["b_lo95"] or 0.0) <= Bt <= j["b_hi95"])
        out["check_ok"] += int(bool(j["check_ok"]))
        out["b_over_truth"].append((j["b"] or j["b_hi95"]) / Bt)
    bt = out.pop("b_over_truth")
    out["b_over_truth_range"] = [float(min(bt)), float(max(bt))]
    return {"case": "rigctl on ADIS16405 ax-like records", "n": nsim, **out}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", help="files, recordings and rigctl's JSON here (reused when present)")
    ap.add_argument("--sim", type=int, default=0, help="simulated records per case (5.)")
    ap.add_argument("--sim-adis", type=int, default=None,
                    help="simulated records per ADIS16405-like case (default: --sim // 3)")
    ap.add_argument("--sim-only", action="store_true", help="skip the five rows (1.-4.)")
    ap.add_argument("--sim-cases", help="comma-separated words; only the simulated cases whose name holds one")
    ap.add_argument("--sim-judge", action="store_true",
                    help="with --keep: judge the simulated records kept there (none drawn)")
    ap.add_argument("--sim-rigctl", type=int, default=0,
                    help="simulated OCXO-like records through rigctl itself (5.)")
    ap.add_argument("--sim-rigctl-adis", type=int, default=0,
                    help="simulated ADIS16405 ax-like records through rigctl itself (5.)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    tmpd = None if args.keep else tempfile.TemporaryDirectory()
    keep = Path(args.keep or tmpd.name)
    keep.mkdir(parents=True, exist_ok=True)
    data = load(keep)
    rows = [] if args.sim_only else [analyse_row(data, keep, *row) for row in ROWS]
    for r in rows:
        print(json.dumps(r, default=float))
    sims = []
    if args.sim or args.sim_adis or args.sim_judge:
        ax_ms = np.asarray(rigctl_json(keep, data[("ADIS16405", "ax")][2], ADIS_COLS, None, "default", "ax")["m"], int)
        gx_ms = np.asarray(rigctl_json(keep, data[("ADIS16405", "gx")][2], ADIS_COLS, None, "octave", "gx")["m"], int)
        o_txt = data[("OCXO", "gx")][2]
        od = np.asarray(rigctl_json(keep, o_txt, OCXO_COLS, None, "default", "gx")["m"], int)
        oo = np.asarray(rigctl_json(keep, o_txt, OCXO_COLS, None, "octave", "gx")["m"], int)
        for case in (("OCXO-like default", 19982, 1.0, od, 0.0, 6.4e-12, 2.7e-13, 4.3e-11, 1.0, TERMS["OCXO"]),
                     ("OCXO-like octave", 19982, 1.0, oo, 0.0, 6.4e-12, 2.7e-13, 4.3e-11, 1.0, TERMS["OCXO"]),
                     ("ADIS16405 ax-like default", 10 ** 6, 0.01, ax_ms, 4.3e-3, 3.5e-3, 4.2e-4, 0.0, 0.05, TERMS["ADIS16405"]),
                     ("ADIS16405 gx-like octave", 10 ** 6, 0.01, gx_ms, 6.8e-4, 1.5e-4, 7e-6, 0.0, 0.05, TERMS["ADIS16405"])):
            nad = args.sim_adis if args.sim_adis is not None else max(1, args.sim // 3)
            if not (args.sim if case[1] < 10 ** 5 else nad) and not args.sim_judge:
                continue
            if args.sim_cases and not any(w in case[0] for w in args.sim_cases.split(",")):
                continue
            sims.append(simulate(*case, nsim=args.sim if case[1] < 10 ** 5 else nad,
                                 keep=keep if args.keep else None, judge_only=args.sim_judge))
            print(json.dumps(sims[-1]), flush=True)
    if args.sim_rigctl:
        sims.append(simulate_rigctl(keep, args.sim_rigctl))
        print(json.dumps(sims[-1]), flush=True)
    if args.sim_rigctl_adis:
        sims.append(simulate_rigctl_adis(keep, args.sim_rigctl_adis))
        print(json.dumps(sims[-1]), flush=True)
    if args.keep:
        (keep / "allan_floor_quiet.json").write_text(json.dumps({"rows": rows, "sims": sims}, indent=1, default=float))
    print(json.dumps({"rows": len(rows),
                      "rigctl_quiet_ok": sum(r.get("quiet", {}).get("rigctl_quiet_verdict") == "ok" for r in rows),
                      "best_at_floor_worst_depth_max": max((r["whole"]["best_at_floor"]["worst_depth_floor"] for r in rows),
                                                           default=None),
                      "sims": len(sims), "wall_s": round(time.perf_counter() - t0, 1)}))


if __name__ == "__main__":
    sys.exit(main())
