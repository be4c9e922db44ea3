"""Prototype: a spectral test for a first-order Gauss-Markov rate beside power-law noise
(docs/allan.md, "Detection limits"), measured before anything goes into rigctl.

    python benchmarks/allan_gm_spectral.py [--null 400] [--fa 50] [--power 40]

The test (``SpectralGM``), on the rate samples y (n at fs):

* the samples' linear trend removed (R's ramp and the offset), a Hann taper, the periodogram;
  its ordinates between ``f_lo`` = 3 / T and ``f_hi`` = fs / 20 averaged in bands of ~4 %
  of f (at least one Fourier bin): a band mean of k Hann-tapered ordinates is taken as Gamma
  with k / 1.944 degrees of freedom per half (adjacent Hann ordinates correlate 2/3 and 1/6:
  1 + 2 (4/9 + 1/36) = 1.944);
* Whittle's likelihood of the band means under the power-law model of rigctl's fit
  (one-sided rate PSD h2 f^2 + h0 + h-1 / f + h-2 / f^2, all >= 0: Q, N, B, K) and under the
  same plus a Gauss-Markov Lorentzian 4 sigma^2 Tc / (1 + (2 pi f Tc)^2) (sigma^2 >= 0), Tc on
  a grid of 4 per octave with the corner 1 / (2 pi Tc) between 2 f_lo and f_hi / 4;
* the statistic: twice the largest log-likelihood gain over Tc; its alarm threshold is the
  ``1 - alpha`` point of the statistic on ``--null`` records drawn from a mix of power-law
  families (below), seeds disjoint from those the false alarms are counted on.

Records (5 minutes at 100 Hz, tests/test_allan_check_bounds.py's sampling):

* ``gm``: tests/test_allan_check_bounds.py's white (N 0.2 deg/sqrt(h)) + flicker (B 5 deg/h)
  + a Gauss-Markov rate sigma F x B, Tc 2 s, seeds 0..39 (the doc's 40-record protocol); the
  power is counted there, and on the seeds where ``rigctl allan`` is silent
  (benchmarks/allan_gm_silent.py: 2 6 7 10 12 25 32 35);
* pure power-law families (no Gauss-Markov), for the null and the false alarms:
  ``wf`` the same white + flicker (circulant, as in the test file);
  ``wfk`` white + flicker shaped on a circle 8x the record (not periodic over it) + random walk
  K 3 deg/h/sqrt(h) (configs/sim.yaml's gyro);
  ``wk`` white 0.3 deg/sqrt(h) + random walk 40 deg/h/sqrt(h) (tests/test_allan_false_alarms.py's);
  ``wf_bw`` ``wfk``'s noise drawn at 1 kHz through a 2nd-order Butterworth at 40 Hz, every 10th
  sample kept (an IMU's anti-aliasing filter at 0.8 of the output's Nyquist);
  ``wq`` white + flicker + white phase noise (quantization: Q 1e-6 rad).

Last line: one JSON object.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
from scipy.optimize import minimize  # noqa: E402
from scipy.signal import butter, lfilter  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
import test_allan_check_bounds as WF  # noqa: E402

DEG = math.pi / 180.0
FS, N = WF.FS, WF.N_SAMPLES
K_SIM = 3.0 * DEG / 3600.0 / 60.0
N_FA, K_FA = 0.3 * DEG / 60.0, 40.0 * DEG / 3600.0 / 60.0
SILENT = (2, 6, 7, 10, 12, 25, 32, 35)
HANN_VIF = 1.0 + 2.0 * (4.0 / 9.0 + 1.0 / 36.0)


class SpectralGM:
    """Whittle likelihood-ratio statistic for a Gauss-Markov Lorentzian beside h2 f^2 + h0 +
    h-1 / f + h-2 / f^2 on the Hann-tapered periodogram's band means (see the module)."""

    def __init__(self, n: int, fs: float, f_lo: float | None = None, f_hi: float | None = None,
                 rel_width: float = 0.04, per_octave: int = 4):
        self.n, self.fs = n, fs
        t = n / fs
        f_lo = 3.0 / t if f_lo is None else f_lo
        f_hi = fs / 20.0 if f_hi is None else f_hi
        f = np.fft.rfftfreq(n, 1.0 / fs)
        k = np.flatnonzero((f >= f_lo) & (f <= f_hi))
        edges = [k[0]]
        while edges[-1] <= k[-1]:
            edges.append(edges[-1] + max(1, int(round(rel_width * edges[-1]))))
        edges[-1] = min(edges[-1], k[-1] + 1)
        self.edges = np.array(edges)
        self.k = np.diff(self.edges).astype(float)
        self.nu = self.k / HANN_VIF  # Gamma shape of each band mean
        fb = [f[a:b] for a, b in zip(self.edges[:-1], self.edges[1:])]
        self.fc = np.array([x.mean() for x in fb])
        cols = [lambda x: x * x, lambda x: np.ones_like(x), lambda x: 1.0 / x,
                lambda x: 1.0 / (x * x)]
        self.h0 = np.array([[c(x).mean() for x in fb] for c in cols])
        self.tcs = 2.0 ** (np.arange(
            math.ceil(per_octave * math.log2(4.0 / (2 * math.pi * f_hi))),
            math.floor(per_octave * math.log2(1.0 / (2 * math.pi * 2 * f_lo))) + 1) / per_octave)
        self.g = np.array([[np.mean(4.0 * tc / (1.0 + (2.0 * math.pi * x * tc) ** 2)) for x in fb]
                           for tc in self.tcs])
        self.win = np.hanning(n)
        self.win_norm = 2.0 / (fs * np.sum(self.win ** 2))  # one-sided PSD

    def band_means(self, y: np.ndarray) -> np.ndarray:
        t = np.arange(y.size, dtype=float)
        r = y - np.polyval(np.polyfit(t, y, 1), t)
        p = np.abs(np.fft.rfft(r * self.win)) ** 2 * self.win_norm
        c = np.concatenate(([0.0], np.cumsum(p)))
        return (c[self.edges[1:]] - c[self.edges[:-1]]) / self.k

    def _nll(self, ib: np.ndarray, h: np.ndarray, x0s: list[np.ndarray] | None = None
             ) -> tuple[float, np.ndarray]:
        """Least Whittle negative log-likelihood over non-negative levels of the rows of h
        (starts ``x0s`` in h's units; default: each row alone and an even mix)."""
        sc = np.array([float(np.median(ib / np.maximum(r, 1e-300))) if np.any(r > 0) else 1.0
                       for r in h])
        sc = np.where(np.isfinite(sc) & (sc > 0), sc, 1.0)
        hs = h * sc[:, None]

        def f(th: np.ndarray) -> tuple[float, np.ndarray]:
            s = np.maximum(th @ hs, 1e-12 * float(np.mean(ib)))
            return (float(np.sum(self.nu * (np.log(s) + ib / s))),
                    hs @ (self.nu * (1.0 / s - ib / s ** 2)))
        best = None
        # starts: each column alone at its median ratio, and an even mix
        starts = ([np.eye(len(hs))[i] + 1e-3 for i in range(len(hs))] + [np.full(len(hs), 0.25)]
                  if x0s is None else [x / sc for x in x0s])
        for x0 in starts:
            r = minimize(f, x0, jac=True, method="L-BFGS-B", bounds=[(0.0, None)] * len(hs))
            if best is None or r.fun < best.fun:
                best = r
        return float(best.fun), best.x * sc

    def stat(self, y: np.ndarray) -> dict:
        ib = self.band_means(y)
        l0, th0 = self._nll(ib, self.h0)
        best = (0.0, math.nan, 0.0)
        for tc, g in zip(self.tcs, self.g):
            # two starts: the null's levels with a small Gauss-Markov level, and the
            # Gauss-Markov shape taking half of the power where it peaks
            gsc = float(np.median(ib / g))
            l1, th = self._nll(ib, np.vstack((self.h0, g)),
                               [np.append(th0, 1e-3 * gsc), np.append(0.5 * th0, 0.5 * gsc)])
            d = 2.0 * (l0 - l1)
            if d > best[0]:
                best = (d, float(tc), float(th[-1]))
        return {"stat": best[0], "tc_s": best[1], "sigma_si": math.sqrt(max(best[2], 0.0))}


def flicker_circle(rng: np.random.Generator, n: int, fs: float, b: float, circle: int = 8
                   ) -> np.ndarray:
    nc = circle * n
    f = np.fft.rfftfreq(nc, 1.0 / fs)
    amp = np.zeros(f.size)
    amp[1:] = np.sqrt(b ** 2 / (2.0 * math.pi * f[1:]))
    spec = rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)
    return np.fft.irfft(spec * amp * math.sqrt(nc * fs / 4.0), nc)[:n]


def family(kind: str, seed: int) -> np.ndarray:
    """One 5-minute record at 100 Hz of a pure power-law family (module docstring)."""
    rng = np.random.default_rng(seed)
    if kind == "wf":
        return WF._noise(seed)
    if kind == "wk":
        return (rng.standard_normal(N) * N_FA * math.sqrt(FS)
                + np.cumsum(rng.standard_normal(N)) * K_FA / math.sqrt(FS))
    if kind == "wf_bw":
        up = 10
        fs = FS * up
        y = (rng.standard_normal(N * up) * WF.N_TRUE * math.sqrt(fs)
             + flicker_circle(rng, N * up, fs, WF.B_TRUE)
             + np.cumsum(rng.standard_normal(N * up)) * K_SIM / math.sqrt(fs))
        bb, aa = butter(2, 40.0 / (fs / 2.0))
        return lfilter(bb, aa, y)[::up]
    y = (rng.standard_normal(N) * WF.N_TRUE * math.sqrt(FS) + flicker_circle(rng, N, FS, WF.B_TRUE))
    if kind == "wfk":
        return y + np.cumsum(rng.standard_normal(N)) * K_SIM / math.sqrt(FS)
    if kind == "wq":  # white phase noise Q: rate = diff(phase) / tau0
        q = 1e-6 * rng.standard_normal(N + 1)
        return y + np.diff(q) * FS
    raise ValueError(kind)


FAMILIES = ("wf", "wfk", "wk", "wf_bw", "wq")


def whittle_gain(free: tuple[str, ...], f_max: float, sigma: float, tc: float = 2.0) -> float:
    """Expected likelihood-ratio gain (sigma^2 / sd(sigma^2))^2 of Whittle's likelihood for a
    Gauss-Markov term of known Tc beside the power-law levels ``free`` (of Q, N, B, K), over
    the Fourier frequencies up to ``f_max``, at the truth of the ``gm`` records (Fisher
    information sum_f dS_i dS_j / S^2; the sampled AR(1)'s spectrum)."""
    f = np.fft.rfftfreq(N, 1.0 / FS)[1:N // 2]
    f = f[f <= f_max]
    a = math.exp(-1.0 / (FS * tc))
    g = (1.0 - a * a) / np.abs(1.0 - a * np.exp(-2j * math.pi * f / FS)) ** 2
    s = WF.N_TRUE ** 2 * FS + FS * WF.B_TRUE ** 2 / (4.0 * math.pi * f) + sigma ** 2 * g
    shape = {"Q": f * f, "N": np.ones_like(f), "B": 1.0 / f, "K": 1.0 / (f * f)}
    cols = np.array([shape[k] for k in free] + [g]) / s
    info = cols @ cols.T
    sc = np.sqrt(np.diag(info))
    sd = math.sqrt(np.linalg.inv(info / np.outer(sc, sc))[-1, -1]) / sc[-1]
    return (sigma ** 2 / sd) ** 2


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--null", type=int, default=400, help="records for the threshold (mix)")
    ap.add_argument("--fa", type=int, default=40, help="records per family for false alarms")
    ap.add_argument("--power", type=int, default=40)
    ap.add_argument("--size", type=float, default=4.0)
    ap.add_argument("--alpha", type=float, default=0.01)
    ap.add_argument("--f-hi", type=float, default=None)
    a = ap.parse_args()
    t0 = time.perf_counter()
    sg = SpectralGM(N, FS, f_hi=a.f_hi)
    gains = {f"{''.join(fr)}_{fm:g}Hz": round(whittle_gain(fr, fm, a.size * WF.B_TRUE), 2)
             for fr in (("N", "B"), ("N", "B", "K"), ("Q", "N", "B", "K"))
             for fm in (FS / 2, FS / 8, FS / 20)}
    print("Whittle's expected gain, Tc known (free levels, band): " + json.dumps(gains),
          flush=True)
    print(f"bands {sg.k.size}, f {sg.fc[0]:.4g}-{sg.fc[-1]:.4g} Hz, Tc {sg.tcs[0]:.3g}-"
          f"{sg.tcs[-1]:.3g} s ({sg.tcs.size})", flush=True)
    null = []
    for i in range(a.null):
        null.append(sg.stat(family(FAMILIES[i % len(FAMILIES)], 900_000 + i))["stat"])
    null = np.array(null)
    thr = float(np.quantile(null, 1.0 - a.alpha))
    by_fam = {f: null[i::len(FAMILIES)] for i, f in enumerate(FAMILIES)}
    print(f"threshold ({100 * (1 - a.alpha):.0f} % of {a.null} null records) {thr:.2f}; per "
          "family 99 % points " + ", ".join(f"{k} {np.quantile(v, 0.99):.2f}"
                                             for k, v in by_fam.items()), flush=True)
    out: dict = {"whittle_gain": gains, "threshold": thr, "alpha": a.alpha, "null": a.null, "bands": int(sg.k.size),
                 "f_hz": [float(sg.fc[0]), float(sg.fc[-1])],
                 "tc_grid_s": [float(sg.tcs[0]), float(sg.tcs[-1])], "fa": {}}
    for kind in FAMILIES:
        st = [sg.stat(family(kind, 100_000 + s))["stat"] for s in range(a.fa)]
        out["fa"][kind] = int(sum(v > thr for v in st))
        print(f"false alarms {kind}: {out['fa'][kind]} of {a.fa} (max stat {max(st):.2f})",
              flush=True)
    found, rows = 0, []
    for s in range(a.power):
        r = sg.stat(WF._noise(s, gm=(a.size * WF.B_TRUE, 2.0)))
        r["found"] = r["stat"] > thr
        found += r["found"]
        rows.append({"seed": s, **r})
        if s in SILENT:
            print(f"  silent seed {s}: stat {r['stat']:.1f} Tc {r['tc_s']:.3g} s sigma "
                  f"{r['sigma_si'] / WF.B_TRUE:.2f} B -> {'found' if r['found'] else 'missed'}",
                  flush=True)
    out["power"] = {"found": found, "of": a.power,
                    "silent_found": sum(r["found"] for r in rows if r["seed"] in SILENT),
                    "tc_s": [min(r["tc_s"] for r in rows if r["found"]),
                             max(r["tc_s"] for r in rows if r["found"])] if found else None,
                    "sigma_b": [min(r["sigma_si"] for r in rows if r["found"]) / WF.B_TRUE,
                                max(r["sigma_si"] for r in rows if r["found"]) / WF.B_TRUE]
                    if found else None}
    print(f"power at sigma {a.size} B, Tc 2 s: {found} of {a.power}; on the 8 silent: "
          f"{out['power']['silent_found']}", flush=True)
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
