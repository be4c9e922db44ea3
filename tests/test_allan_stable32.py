"""Allan-family deviations, term counts, intervals and noise ID against Stable32 tables."""
from __future__ import annotations

import gzip
import json
from pathlib import Path

import numpy as np
import pytest

from rigctl.solvers import allan as A
from rigctl.solvers import allan_edf as E

REF = "stable32-reference"
DATASETS = {
    "phasedat": ("phasedat/PHASE.DAT",
                 [f"phasedat/phase_dat_{k}.txt" for k in
                  ("adev", "adev_octave", "oadev", "oadev_octave", "mdev", "mdev_octave", "tdev",
                   "tdev_octave", "hdev", "hdev_octave", "ohdev", "ohdev_octave", "totdev",
                   "totdev_octave")]),
    "Cs5071A": ("Cs5071A/5071A_phase.txt.gz",
                [f"Cs5071A/{k}_{s}.txt" for k in
                 ("adev", "oadev", "mdev", "tdev", "hdev", "ohdev", "totdev")
                 for s in ("decade", "all")]),
    "Keysight53230A": ("Keysight53230A_ti_noise_floor/tic_phase.txt",
                       [f"Keysight53230A_ti_noise_floor/tic_{k}.txt" for k in
                        ("adev", "oadev", "mdev", "tdev", "hdev", "ohdev", "totdev")]),
}
TABLES = [(ds, t) for ds, (_, tabs) in DATASETS.items() for t in tabs]
#: tables whose Alpha column was not produced by Stable32's automatic noise ID: the Cs5071A
#: decade totdev run reports alpha 0 at every tau, even at tau = 1..10 s where every other
#: Cs5071A table (and its all-tau totdev table) identifies white PM (alpha 2); the Keysight
#: adev table disagrees with the lag-1 ID in 9 rows where all other Keysight tables agree.
FIXED_ALPHA_TABLES = {"Cs5071A/totdev_decade.txt", "Keysight53230A_ti_noise_floor/tic_adev.txt"}

_PHASE_CACHE: dict[str, np.ndarray] = {}


def _phase(root: Path, dataset: str) -> np.ndarray:
    if dataset not in _PHASE_CACHE:
        p = root / REF / DATASETS[dataset][0]
        opener = gzip.open if p.suffix == ".gz" else open
        with opener(p, "rt") as f:
            vals = [float(line.split()[0]) for line in f
                    if line.strip() and not line.lstrip().startswith("#")]
        _PHASE_CACHE[dataset] = np.array(vals)
    return _PHASE_CACHE[dataset]


def _table(root: Path, name: str) -> np.ndarray:
    rows = [[float(v) for v in line.split()] for line in (root / REF / name).read_text().splitlines()
            if line.strip() and not line.lstrip().startswith("#")]
    return np.array(rows)


def _kind(name: str) -> str:
    stem = Path(name).stem.replace("phase_dat_", "").replace("tic_", "")
    return stem.split("_")[0]


_RESULT_CACHE: dict[str, tuple] = {}


def _compute(root: Path, dataset: str, name: str):
    """Phase, table, kind, factors and our deviation for one table (cached per session)."""
    if name not in _RESULT_CACHE:
        _RESULT_CACHE[name] = _compute_uncached(root, dataset, name)
    return _RESULT_CACHE[name]


def _compute_uncached(root: Path, dataset: str, name: str):
    x = _phase(root, dataset)
    t = _table(root, name)
    kind = _kind(name)
    ms = t[:, 0].astype(np.int64)
    kw = {"mode": "exact"} if kind == "oadev" else {}
    res = A.DEVIATIONS[kind](x, 1.0, ms, data_type="phase", **kw)
    return x, t, kind, ms, res


@pytest.mark.parametrize("dataset,name", TABLES, ids=[t for _, t in TABLES])
def test_deviation_and_term_count(shared_data: Path, dataset: str, name: str) -> None:
    x, t, kind, ms, res = _compute(shared_data, dataset, name)
    assert np.array_equal(res.m, ms)
    np.testing.assert_allclose(res.tau_s, t[:, 1], rtol=1e-4)
    np.testing.assert_allclose(res.dev, t[:, 5], rtol=1e-4, atol=0)
    assert np.array_equal(res.n_terms, t[:, 2].astype(np.int64))


@pytest.mark.parametrize("dataset,name", TABLES, ids=[t for _, t in TABLES])
def test_interval_bounds(shared_data: Path, dataset: str, name: str) -> None:
    """Min/Max Sigma from Greenhall's EDF for the table's noise type, within 1e-3."""
    x, t, kind, ms, res = _compute(shared_data, dataset, name)
    if not np.any(t[:, 4] > 0):
        pytest.skip("table has no interval columns (Stable32 wrote zeros)")
    c = E.confidence(kind, x, ms, res.dev, alphas=t[:, 3].astype(np.int64))
    np.testing.assert_allclose(c["lo68"], t[:, 4], rtol=1e-3)
    np.testing.assert_allclose(c["hi68"], t[:, 6], rtol=1e-3)
    assert np.all(c["lo95"] < c["lo68"]) and np.all(c["hi95"] > c["hi68"])


@pytest.mark.parametrize("dataset,name", TABLES, ids=[t for _, t in TABLES])
def test_noise_id_lag1_regime(shared_data: Path, dataset: str, name: str) -> None:
    """Where Stable32 uses the lag-1 autocorrelation (>= 30 points), alpha matches exactly."""
    if name in FIXED_ALPHA_TABLES:
        pytest.skip("Alpha column of this table is not Stable32's automatic ID (see above)")
    x, t, kind, ms, _ = _compute(shared_data, dataset, name)
    n_pts = (x.size - 1) // ms + (0 if kind in ("adev", "hdev") else 1)
    sel = n_pts >= 30
    ids = np.array([E.noise_id(x, int(m), kind) for m in ms[sel]])
    assert np.array_equal(ids, t[sel, 3].astype(np.int64))


@pytest.mark.parametrize("name", ["Cs5071A/adev_decade.txt", "Cs5071A/hdev_decade.txt"])
def test_noise_id_every_row_nonoverlapped(shared_data: Path, name: str) -> None:
    """Including the long taus decided by the B1 ratio fallback (fewer than 30 intervals)."""
    x, t, kind, ms, _ = _compute(shared_data, "Cs5071A", name)
    ids = np.array([E.noise_id(x, int(m), kind) for m in ms])
    assert np.array_equal(ids, t[:, 3].astype(np.int64))


def test_noise_id_fallback_agreement(shared_data: Path) -> None:
    """B1/R(n) fallback (fewer than 30 points): agreement with Stable32 over all tables.

    Stable32's exact fallback rule for the overlapping estimators is not published; ours
    follows SP 1065 (B1 with the non-overlapped Allan variance, R(n) for PM). Non-overlapped
    adev/hdev agree in >= 85 % of these rows; the figure is asserted so it cannot regress.
    """
    agree = {"nonoverlapped": [0, 0], "overlapped": [0, 0]}
    for dataset, name in TABLES:
        if name in FIXED_ALPHA_TABLES or not name.endswith(("all.txt", "dev.txt")):
            continue
        x, t, kind, ms, _ = _compute(shared_data, dataset, name)
        n_pts = (x.size - 1) // ms + (0 if kind in ("adev", "hdev") else 1)
        key = "nonoverlapped" if kind in ("adev", "hdev") else "overlapped"
        for m, a in zip(ms[n_pts < 30], t[n_pts < 30, 3]):
            agree[key][0] += int(E.noise_id(x, int(m), kind) == int(a))
            agree[key][1] += 1
    frac = {k: v[0] / v[1] for k, v in agree.items()}
    assert frac["nonoverlapped"] >= 0.85, frac
    assert frac["overlapped"] >= 0.40, frac


def test_nbs14(shared_data: Path) -> None:
    ref = json.loads((shared_data / REF / "nbs14_reference.json").read_text())
    ten = ref["nbs14_10point"]
    y = np.array(ten["frequency"], dtype=float)
    m = np.array(ten["taus"])
    for kind in ("adev", "oadev", "mdev", "hdev", "ohdev", "tdev"):
        kw = {"mode": "exact"} if kind == "oadev" else {}
        r = A.DEVIATIONS[kind](y, 1.0, m, data_type="rate", **kw)
        np.testing.assert_allclose(r.dev, ten[kind], rtol=1e-6, err_msg=kind)
    r = A.totdev(y, 1.0, m, data_type="rate")
    np.testing.assert_allclose(r.dev, ten["totdev_sp1065_p107"], rtol=1e-6)

    big = ref["nbs14_1000point"]
    n = [1234567890]
    for _ in range(1000):
        n.append((16807 * n[-1]) % 2147483647)
    assert n[1:4] == [395529916, 1209410747, 633705974]
    y = np.array(n[:1000], dtype=float) / 2147483647.0
    m = np.array(big["taus"])
    for kind in ("adev", "oadev", "mdev", "hdev", "ohdev", "tdev"):
        kw = {"mode": "exact"} if kind == "oadev" else {}
        r = A.DEVIATIONS[kind](y, 1.0, m, data_type="rate", **kw)
        np.testing.assert_allclose(r.dev, big[kind], rtol=1e-6, err_msg=kind)
    r = A.totdev(y, 1.0, m, data_type="rate")
    np.testing.assert_allclose(r.dev, big["totdev_sp1065_p108"], rtol=1e-6)
