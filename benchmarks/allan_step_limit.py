"""Can a rate step be seen at all? The best test that knows the noise model against rigctl's
checks, by step size and record length (docs/allan.md, "Detection limits: a rate step, a
Gauss-Markov bump").

Records (block means of the rate, ``BLOCK_S`` each, in rad/s; everything in plain numpy): the
default emulated gyro (configs/sim.yaml: N 0.2 deg/sqrt(h), B 5 deg/h as flicker, K 3
deg/h/sqrt(h); the records of benchmarks/allan_completed_dof.py have the same N and B) as
white + flicker + random walk. The flicker (one-sided PSD B^2 / (2 pi f)) is FFT-shaped on a
circle ``CIRCLE`` times the record and cut, so that it is stationary and not periodic over the
record (a circle of the record's own length makes the end continue into the start, which a
test that knows it uses: the step's sd at half of a 5-minute record 0.54 B instead of 0.65 B).
A step of F x B is added at half the record.

**The best test** (``oracle``): the generalized likelihood ratio for a step at an unknown time
against the exact Gaussian model of the records (covariance Sigma of their block means,
coarsened to ``N_COARSE`` blocks, from the flicker's autocovariance, the white noise and the
random walk), with the rate's offset and a ramp as nuisance parameters (R is in rigctl's model:
a ramp is not a misfit; ``--no-trend`` drops it), the step time scanned over 5-95 % of the
record::

    z_k = s_k' P y / sqrt(s_k' P s_k),   P = Sigma^-1 - Sigma^-1 X (X' Sigma^-1 X)^-1 X' Sigma^-1

(X the offset and ramp, s_k the step at block k), max_k |z_k| against its 99 % point under no
step, from ``--null`` records drawn from N(0, Sigma). Its power is the best any test can reach
at a 1 % false-alarm rate (knowing N, B and K exactly; rigctl does not). Also printed: the
step's sd at half the record, known time (sd_mid: the Cramer-Rao bound).

**rigctl's excursion detector** (:func:`rigctl.solvers.allan_excursions.find_excursions`) on
the same block means: found when an excursion or level shift starts or ends within
max(60 s, T / 16) of the step; its false alarms (any detection) on the same records without it.
It runs on records of 960 s or more (30 s windows, 32 of them).

``--emulator``: the records are the emulator's own (:func:`emulated`; its flicker is a
pole-zero bank over a band of correlation times, so Sigma above is not exactly theirs: the
best test's numbers are then indicative, the detector's are the point).

**The self-check** (5-minute records at 100 Hz, ``--fit-seeds``): the benchmark's own records
(tests/test_allan_check_bounds.py's generator, benchmarks/allan_completed_dof.py's ``stepF``),
fit_terms' check failing (``ok`` False); and rigctl's step test for records too short for
the detector (:func:`rigctl.solvers.allan_step.step_test`), with the levels from that fit
(:func:`check_table`).

The last line is one JSON object.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
from scipy.linalg import cho_factor, cho_solve, solve_triangular  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent

from rigctl.solvers import allan_excursions as EX  # noqa: E402
from rigctl.solvers import allan_step as AS  # noqa: E402

DEG = math.pi / 180.0
#: the default emulated gyro (configs/sim.yaml), SI
N_SI = 0.2 * DEG / 60.0  # rad/sqrt(s)
B_SI = 5.0 * DEG / 3600.0  # rad/s
K_SI = 3.0 * DEG / 3600.0 / 60.0  # rad/s/sqrt(s)
#: block length of the records (s)
BLOCK_S = 0.5
#: the flicker is shaped on a circle this many times the record, then cut
CIRCLE = 8
#: the best test works on this many block means (a step's information is at low frequencies)
N_COARSE = 300


def record(seed: int, t_s: float, k_si: float = K_SI) -> np.ndarray:
    """Block means (BLOCK_S) of white (N) + flicker (B) + random walk (K) rate noise, t_s long."""
    rng = np.random.default_rng(seed)
    nb = int(round(t_s / BLOCK_S))
    white = rng.standard_normal(nb) * N_SI / math.sqrt(BLOCK_S)
    nc = CIRCLE * nb
    f = np.fft.rfftfreq(nc, BLOCK_S)
    amp = np.zeros(f.size)
    amp[1:] = np.sqrt(B_SI ** 2 / (2.0 * math.pi * f[1:]))
    spec = rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)
    # one-sided PSD S: irfft coefficients of variance S n / (2 dt) per complex bin (E|X|^2)
    flick = np.fft.irfft(spec * amp * math.sqrt(nc / (4.0 * BLOCK_S)), nc)[:nb]
    rw = np.cumsum(rng.standard_normal(nb)) * k_si * math.sqrt(BLOCK_S)
    return white + flick + rw


def emulated(seed: int, t_s: float, rate_hz: float = 10.0) -> np.ndarray:
    """Block means (BLOCK_S) of the default emulated IMU's x gyro (configs/sim.yaml, drawn by
    rigctl.sim.noise.NoiseGenerator at ``rate_hz``: N, B as its pole-zero flicker, K), in rad/s."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import allan_quickstart_cov as QS  # noqa: E402

    from rigctl.sim.noise import NoiseGenerator  # noqa: E402
    _, noise = QS.default_noise()
    k = int(round(BLOCK_S * rate_hz))
    n = int(round(t_s * rate_hz)) // k * k
    y = NoiseGenerator(noise["gyro"], rate_hz, np.random.SeedSequence([seed, 1])).next(n)[:, 0]
    return y.reshape(-1, k).mean(axis=1)


def coarse_sigma(nb: int, n_coarse: int = N_COARSE, k_si: float = K_SI, n_si: float = N_SI,
                 b_si: float = B_SI, block_s: float = BLOCK_S) -> np.ndarray:
    """Covariance of the means of n_coarse equal groups of :func:`record`'s nb blocks
    (rigctl.solvers.allan_step.group_sigma: the same model, the same circle)."""
    return AS.group_sigma(nb, block_s, n_si, b_si, k_si, 0.0, n_coarse, CIRCLE)


StepGLR = AS.StepGLR


def coarsen(y: np.ndarray, n_coarse: int = N_COARSE) -> np.ndarray:
    return AS.group_means(y, n_coarse)


def found_at(r: dict, t_step: float, tol: float) -> bool:
    """An excursion or level shift of the detector's result within tol of t_step (s)."""
    return any(abs(e["start_s"] - t_step) <= tol or abs(e["end_s"] - t_step) <= tol
               for e in r.get("excursions", []))


def step_table(lengths: list[float], sizes: list[float], seeds: int, n_null: int,
               trend: bool, source: str = "model") -> dict:
    out: dict = {}
    for t_s in lengths:
        nb = int(round(t_s / BLOCK_S))
        glr = StepGLR(coarse_sigma(nb), trend)
        rng = np.random.default_rng(12345)
        null = glr.chol @ rng.standard_normal((N_COARSE, n_null))
        thr = float(np.quantile(glr.stat(null.T), 0.99))
        t_step = (nb // 2) * BLOCK_S
        tol = max(60.0, t_s / 16.0)
        ys = [record(1000 + s, t_s) if source == "model" else emulated(1000 + s, t_s)
              for s in range(seeds)]
        fa_ex = sum(bool(EX.find_excursions(y, BLOCK_S).get("excursions")) for y in ys)
        row = {"sd_mid_B": glr.sd_at(N_COARSE // 2) / B_SI, "threshold_z": thr,
               "oracle_null": int(np.sum(glr.stat(np.array([coarsen(y) for y in ys])) > thr)),
               "excursions_null": fa_ex, "tested": bool(EX.find_excursions(ys[0], BLOCK_S)["tested"]),
               "sizes": {}}
        for f in sizes:
            step = np.zeros(nb)
            step[nb // 2:] = f * B_SI
            ws = [y + step for y in ys]
            st = glr.stat(np.array([coarsen(w) for w in ws]))
            ex = sum(found_at(EX.find_excursions(w, BLOCK_S), t_step, tol) for w in ws)
            row["sizes"][f] = {"oracle": int(np.sum(st > thr)), "excursions": int(ex)}
        out[t_s] = row
        print(f"T {t_s:7.0f} s: step sd at half (known time) {row['sd_mid_B']:.3f} B, "
              f"best test's 1 % threshold z {thr:.2f}; no step: best test {row['oracle_null']}, "
              f"excursion detector {fa_ex} of {seeds}"
              + ("" if row["tested"] else " (not run: record < 960 s)"), flush=True)
        for f, v in row["sizes"].items():
            print(f"    step {f:4.1f} B: best test {v['oracle']:4d}, excursion detector "
                  f"{v['excursions']:4d} of {seeds}", flush=True)
    return out


def _upper(c: Any) -> float:
    """A term's 95 % upper end: its interval's when resolved, else its bound (SI)."""
    return float(c.ci95[1]) if c.resolved else float(c.upper95)


def check_table(sizes: list[float], seeds: int) -> dict:
    """The self-check (fit_terms' ``ok``) on the 5-minute benchmark records with a step, and
    rigctl's step test for short records with the levels from that fit
    (:func:`rigctl.solvers.allan_step.step_test`: the 95 % upper ends of Q, N, B and K) on
    0.5 s block means (``plugin``)."""
    WF = _wf()
    from rigctl.solvers import allan_fit as F  # noqa: E402
    out = {}
    tb = 0.5
    k = int(round(tb * WF.FS))
    for f in [0.0] + sizes:
        failed = plug = 0
        for s in range(seeds):
            y = WF._noise(s)
            y[y.size // 2:] += f * WF.B_TRUE
            tau, dev, edf, n_phase = WF._curve(y)
            fit = F.fit_terms(tau, dev, edf, "gyro", tau0=1.0 / WF.FS, n_phase=n_phase)
            failed += not fit["check"]["ok"]
            co = fit["coefficients"]
            yb = y[: y.size // k * k].reshape(-1, k).mean(axis=1)
            plug += AS.step_test(yb, tb, {t: _upper(getattr(co, t)) for t in "QNBK"})["found"]
        out[f] = {"check_failed": failed, "plugin": int(plug)}
        print(f"5 min at 100 Hz, step {f:4.1f} B: self-check failed {failed}, step test with "
              f"the fit's levels {plug} of {seeds}", flush=True)
    return out


def _wf():
    sys.path.insert(0, str(ROOT / "tests"))
    import test_allan_check_bounds as WF  # noqa: E402
    return WF


class GaussMarkovGLR:
    """The best test for a first-order Gauss-Markov rate beside known white + flicker noise
    (the 5-minute records of tests/test_allan_check_bounds.py, whose flicker is circulant: their
    Fourier coefficients are exactly independent, E|Y_f|^2 = n (N^2 fs + fs B^2 / (4 pi f))):
    Whittle's likelihood, the Gauss-Markov spectrum of the AR(1) the records use,
    n sigma^2 (1 - a^2) / |1 - a e^(-i w)|^2 (a = e^(-1 / (fs Tc))), maximized over sigma^2 >= 0
    and Tc on a log grid (0.05-60 s, 4 per octave), twice the log-likelihood gain."""

    def __init__(self, n: int, fs: float, n_si: float, b_si: float):
        f = np.fft.rfftfreq(n, 1.0 / fs)[1:n // 2]
        self.p0 = n * (n_si ** 2 * fs + fs * b_si ** 2 / (4.0 * math.pi * f))
        w = 2.0 * math.pi * f / fs
        self.g = []
        for tc in np.exp(np.arange(math.log(0.05), math.log(60.0), math.log(2.0) / 4)):
            a = math.exp(-1.0 / (fs * tc))
            self.g.append(n * (1.0 - a * a) / np.abs(1.0 - a * np.exp(-1j * w)) ** 2)

    def stat(self, y: np.ndarray) -> float:
        i = np.abs(np.fft.rfft(y - y.mean())[1:self.p0.size + 1]) ** 2
        ll0 = -np.sum(np.log(self.p0) + i / self.p0)
        best = 0.0
        for g in self.g:
            v = 0.0  # Newton steps on sigma^2 >= 0 (the log-likelihood is concave near 0)
            for _ in range(60):
                s = self.p0 + v * g
                d1 = np.sum(g * (i - s) / s ** 2)
                d2 = np.sum(g * g * (s - 2.0 * i) / s ** 3)
                if v == 0.0 and d1 <= 0.0:
                    break
                nv = v - d1 / d2 if d2 < 0.0 else 2.0 * v + 1e-3 * float(np.mean(self.p0 / g))
                nv = max(nv, 0.0)
                if abs(nv - v) <= 1e-9 * max(v, 1e-300):
                    v = nv
                    break
                v = nv
            s = self.p0 + v * g
            best = max(best, 2.0 * float(-np.sum(np.log(s) + i / s) - ll0))
        return best


class FreeGaussMarkovGLR(GaussMarkovGLR):
    """The same likelihood ratio with the white and flicker levels not known (fitted under
    both hypotheses, non-negative): how much of the best test's power is left to a test
    that, like rigctl, must estimate N and B from the record."""

    def _fit(self, i: np.ndarray, g: np.ndarray | None) -> float:
        """The least negative log-likelihood of levels >= 0 of white, 1/f and (with ``g``)
        the Gauss-Markov shape, each column scaled to the data's order for the optimizer."""
        from scipy.optimize import minimize
        f_inv = 1.0 / np.arange(1, i.size + 1)  # the flicker's 1/f shape (f in bins)
        hs = [np.ones_like(i) * float(np.median(self.p0)), f_inv * float(self.p0[0])]
        if g is not None:
            hs.append(g * float(np.median(self.p0) / np.max(g)))
        h = np.array(hs)

        def nll(th: np.ndarray) -> tuple[float, np.ndarray]:
            s = th @ h
            return float(np.sum(np.log(s) + i / s)), h @ (1.0 / s - i / s ** 2)
        x0 = np.array([1.0, 0.1] + ([0.1] if g is not None else []))
        r = minimize(nll, x0, jac=True, method="L-BFGS-B",
                     bounds=[(1e-6, None), (0.0, None)] + ([(0.0, None)] if g is not None else []))
        return float(r.fun)

    def stat(self, y: np.ndarray) -> float:
        i = np.abs(np.fft.rfft(y - y.mean())[1:self.p0.size + 1]) ** 2
        l0 = self._fit(i, None)
        # Tc on a half-octave grid (the likelihood is smooth in Tc; a quarter of the cost)
        return max(0.0, 2.0 * (l0 - min(self._fit(i, g) for g in self.g[::2])))


def gm_table(sizes: list[float], seeds: int, n_null: int, product: bool) -> dict:
    """The best test, the Gauss-Markov candidate's own test (run on every record) and the
    self-check on the 5-minute records with a Gauss-Markov rate of F x B, Tc 2 s."""
    WF = _wf()
    from rigctl.solvers import allan_fit as F  # noqa: E402
    from rigctl.solvers import allan_gm as GM  # noqa: E402
    glr = GaussMarkovGLR(WF.N_SAMPLES, WF.FS, WF.N_TRUE, WF.B_TRUE)
    thr = float(np.quantile([glr.stat(WF._noise(50000 + s)) for s in range(n_null)], 0.99))
    print(f"Gauss-Markov, 5 min at 100 Hz: the best test's 1 % point {thr:.2f} ({n_null} records)",
          flush=True)
    out: dict = {"threshold": thr, "sizes": {}}
    for f in [0.0] + sizes:
        row = {"oracle": 0, "candidate": 0, "check_failed": 0}
        for s in range(seeds):
            y = WF._noise(s, gm=(f * WF.B_TRUE, 2.0) if f else None)
            row["oracle"] += glr.stat(y) > thr
            tau, dev, edf, n_phase = WF._curve(y)
            fit = F.fit_terms(tau, dev, edf, "gyro", tau0=1.0 / WF.FS, n_phase=n_phase)
            row["check_failed"] += not fit["check"]["ok"]
            row["candidate"] += bool(GM.gm_candidate(tau, dev, edf, 1.0 / WF.FS,
                                                     n_phase).get("detected"))
        row = {k: int(v) for k, v in row.items()}
        if product:
            row.update(gm_product(f, seeds))
        out["sizes"][f] = row
        print(f"    sigma {f:3.1f} B: best test {row['oracle']}, candidate's test "
              f"{row['candidate']}, self-check failed {row['check_failed']} of {seeds}"
              + (f"; rigctl allan: Gauss-Markov term {row['product_gm']}, check failed "
                 f"{row['product_failed']}, silent {row['product_silent']} of {seeds}"
                 if product else ""), flush=True)
    return out


def gm_free_table(sizes: list[float], seeds: int, n_null: int) -> dict:
    """:class:`FreeGaussMarkovGLR` (N and B fitted) on the same 5-minute records: its 99 %
    point from ``n_null`` records without a bump (seeds 50000 +), its power per sigma."""
    WF = _wf()
    glr = FreeGaussMarkovGLR(WF.N_SAMPLES, WF.FS, WF.N_TRUE, WF.B_TRUE)
    thr = float(np.quantile([glr.stat(WF._noise(50000 + s)) for s in range(n_null)], 0.99))
    out: dict = {"threshold": thr, "sizes": {}}
    for f in sizes:
        out["sizes"][f] = int(sum(glr.stat(WF._noise(s, gm=(f * WF.B_TRUE, 2.0))) > thr
                                  for s in range(seeds)))
        print(f"Gauss-Markov sigma {f:3.1f} B, N and B fitted: found {out['sizes'][f]} of "
              f"{seeds} (99 % point {thr:.2f} from {n_null} records)", flush=True)
    return out


def gm_product(f: float, seeds: int) -> dict:
    """``rigctl allan``'s own outcome (rigctl.analysis.allan.compute of a recording) on the
    same records, as the x gyro: a Gauss-Markov term in the fit, its check failed, or neither
    (silent)."""
    import tempfile

    WF = _wf()
    from recording_helpers import write_recording  # noqa: E402

    from rigctl.analysis import allan as AA  # noqa: E402
    got = {"product_gm": 0, "product_failed": 0, "product_silent": 0}
    with tempfile.TemporaryDirectory() as d:
        for s in range(seeds):
            y = WF._noise(s, gm=(f * WF.B_TRUE, 2.0) if f else None)
            g = np.column_stack((y, np.zeros_like(y), np.zeros_like(y)))
            path = Path(d) / f"s{s}.h5"
            write_recording(path, WF.FS, angular_rate=g)
            fit = AA.compute(str(path), ["gx"], 95, False, None, gaps="skip")["axes"]["gx"]["fit"]
            has_gm = bool(fit.get("gm_term"))
            failed = not fit["check"]["ok"]
            got["product_gm"] += has_gm
            got["product_failed"] += failed
            got["product_silent"] += not (has_gm or failed)
            path.unlink()
    return got


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lengths", default="300,1200,3600,14400", help="record lengths (s)")
    ap.add_argument("--sizes", default="1,2,3,4,6,8,12", help="step sizes (x B)")
    ap.add_argument("--seeds", type=int, default=200)
    ap.add_argument("--null", type=int, default=4000, help="null draws for the 99 %% point")
    ap.add_argument("--no-trend", action="store_true", help="the offset only as nuisance")
    ap.add_argument("--emulator", action="store_true",
                    help="records from the emulator's generator (the best test's Sigma is then "
                         "that of the numpy model, not exact)")
    ap.add_argument("--fit-seeds", type=int, default=0,
                    help="self-check and the step test with the fit's levels, 5-min records")
    ap.add_argument("--gm-sizes", default="", help="Gauss-Markov sigma (x B), Tc 2 s")
    ap.add_argument("--gm-seeds", type=int, default=100)
    ap.add_argument("--gm-null", type=int, default=1000)
    ap.add_argument("--product", action="store_true", help="also rigctl allan on recordings")
    ap.add_argument("--gm-free", action="store_true",
                    help="only the Gauss-Markov test with N and B fitted (--gm-sizes, "
                         "--gm-seeds, --gm-null)")
    a = ap.parse_args()
    t0 = time.perf_counter()
    sizes = [float(v) for v in a.sizes.split(",")]
    res = {"steps": step_table([float(v) for v in a.lengths.split(",")], sizes, a.seeds,
                               a.null, not a.no_trend, "emulator" if a.emulator else "model")}
    if a.fit_seeds:
        res["self_check"] = check_table(sizes, a.fit_seeds)
    if a.gm_sizes and a.gm_free:
        res["gauss_markov_free"] = gm_free_table([float(v) for v in a.gm_sizes.split(",")],
                                                 a.gm_seeds, a.gm_null)
    elif a.gm_sizes:
        res["gauss_markov"] = gm_table([float(v) for v in a.gm_sizes.split(",")], a.gm_seeds,
                                       a.gm_null, a.product)
    print(f"{time.perf_counter() - t0:.0f} s")
    print(json.dumps(res))


if __name__ == "__main__":
    main()
