"""Windows left out of the samples (excursions, `drop`) are gaps made on purpose: with gaps
skipped (the default) the Allan sums equal those of the same recording with those rows
missing and /imu/counter jumping over them -- the record's own gap handling (Stable32's) --
and with gaps bridged, those of the rows joined."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from recording_helpers import write_recording
from rigctl.analysis import allan as AA

DROP = [(16_000, 16_384), (30_000, 34_000)]  # one ends at a chunk edge, one spans one


def _series(n: int = 60_000, seed: int = 5) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.standard_normal(n) * 1e-3 + np.cumsum(rng.standard_normal(n)) * 2e-6 + 0.01


def _write(path: Path, y: np.ndarray, counter: np.ndarray) -> None:
    g = np.column_stack([y, np.full(y.size, 1e-3), np.full(y.size, -1e-3)])
    write_recording(path, 100.0, counter=counter.astype(np.uint64), angular_rate=g)


@pytest.mark.parametrize("gaps", ["skip", "bridge"])
def test_drop_is_the_records_gap_handling(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                          gaps: str) -> None:
    monkeypatch.setattr(AA, "CHUNK_ROWS", 8192)
    y = _series()
    keep = np.ones(y.size, dtype=bool)
    for a, b in DROP:
        keep[a:b] = False
    whole, cut = tmp_path / "whole.h5", tmp_path / "cut.h5"
    _write(whole, y, np.arange(y.size))
    # skip: the rows missing, the counter jumping over them (gaps); bridge: the rows joined
    _write(cut, y[keep], np.flatnonzero(keep) if gaps == "skip" else np.arange(int(keep.sum())))
    got = AA.compute_once(str(whole), ["gx"], 40, True, drop=DROP, gaps=gaps)
    ref = AA.compute_once(str(cut), ["gx"], 40, True, gaps="skip")
    g, r = got["axes"]["gx"], ref["axes"]["gx"]
    assert got["n_samples"] == ref["n_samples"] == int(keep.sum())
    np.testing.assert_array_equal(g["m"], r["m"])
    np.testing.assert_allclose(g["adev_rad/s"], r["adev_rad/s"], rtol=1e-9)
    np.testing.assert_array_equal(g["n_terms"], r["n_terms"])
    np.testing.assert_allclose(g["edf"], r["edf"], rtol=1e-9)
    ex = got["gaps"]["excluded"]
    assert ex["rows"] == [list(d) for d in DROP] and ex["samples"] == sum(b - a for a, b in DROP)
    assert ex["handled"] == ("skipped" if gaps == "skip" else "bridged")
    if gaps == "skip":
        assert got["gaps"]["stretches"] == ref["gaps"]["stretches"] == 3


def _pooled_oadev(parts: list[np.ndarray], m: int) -> float:
    """Overlapping Allan deviation pooled over gap-free pieces: every term inside a piece,
    none across (Stable32's gap skipping), written here in numpy."""
    d2, n = 0.0, 0
    for y in parts:
        c = np.concatenate(([0.0], np.cumsum(y)))
        i = np.arange(0, y.size - 2 * m + 1)
        if i.size == 0:
            continue
        d = (c[i + 2 * m] - 2 * c[i + m] + c[i]) / m
        d2 += float(np.sum(d * d))
        n += i.size
    return math.sqrt(0.5 * d2 / n)


@pytest.fixture(scope="module")
def bump_record(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    """A record whose first fifth has rate dips (the quiet stretch test's record, seed 3:
    quiet stretch t = 10000-40000 s) and one more 300 s bump of 8 B at t = 25000 s inside
    the quiet stretch."""
    import test_allan_quiet_stretch as QT

    y = QT.stationary(QT.SEED) + QT.excursions(QT.SEED)[0]
    y[25_000:25_300] += 8.0 * QT.B_TRUE
    rec = tmp_path_factory.mktemp("bump") / "bump.h5"
    write_recording(rec, QT.FS, angular_rate=np.column_stack([y, y, y]))
    return rec, y


def test_quiet_stretch_without_its_excursion(bump_record: tuple[Path, np.ndarray]) -> None:
    """The bump found, and with --excursions exclude (the default) left out of the stretch's
    fit -- whose deviations are then those of the stretch's two pieces, read here in numpy."""
    rec, y = bump_record
    out = {"report": AA.compute(str(rec), ["gx"], "octave", excursions="report"),
           "exclude": AA.compute(str(rec), ["gx"], "octave")}  # the default
    assert out["exclude"]["excursions_mode"] == "exclude"
    r = out["exclude"]["axes"]["gx"]
    found = [e for e in r["excursions"]["excursions"] if e["end_s"] > 24_000 and e["start_s"] < 26_000]
    assert len(found) == 1 and abs(found[0]["start_s"] - 25_000) <= 15 and abs(found[0]["end_s"] - 25_300) <= 15
    q = r["quiet_stretch"]
    assert q["fitted"] and q["t_s"][0] <= 24_000 and q["t_s"][1] >= 26_000
    a, b = found[0]["samples"]
    assert q["excursions_excluded"]["samples"] == [[a, b]]
    assert q["pieces"] == [[q["samples"][0], a], [b, q["samples"][1]]]
    parts = [y[p0:p1] for p0, p1 in q["pieces"]]
    for k in (0, len(q["m"]) // 2, len(q["m"]) - 8):
        m = int(q["m"][k])
        assert q["adev_rad/s"][k] == pytest.approx(_pooled_oadev(parts, m), rel=1e-9)
    # reported only: the stretch keeps it (its deviations are those of the whole stretch)
    qr = out["report"]["axes"]["gx"]["quiet_stretch"]
    assert "excursions_excluded" not in qr and qr["pieces"] == [qr["samples"]]
    assert qr["excursions_inside"] and qr["adev_rad/s"][len(qr["m"]) // 2] == pytest.approx(
        _pooled_oadev([y[slice(*qr["samples"])]], int(qr["m"][len(qr["m"]) // 2])), rel=1e-9)
    # the record's own fit is the same either way (beside, never instead)
    np.testing.assert_array_equal(out["report"]["axes"]["gx"]["adev_rad/s"], r["adev_rad/s"])
    # the text says what was found (in deg/h), and whether the stretch's fit has it
    from rigctl.analysis.allan_text import format_table

    span = f"t = {found[0]['start_s']:.0f}-{found[0]['end_s']:.0f} s"
    size = f"{found[0]['size_deg/h']:+.3g} deg/h"
    t_ex, t_rep = (format_table("gx", out[m]["axes"]["gx"]) for m in ("exclude", "report"))
    assert f"{span} ({found[0]['duration_s']:.0f} s), {size}" in t_ex
    assert "left out of its fit (--excursions exclude" in t_ex
    assert "they are in its fit (--excursions report): to leave them out, --excursions exclude" in t_rep


@pytest.mark.parametrize("gaps", ["longest", "refuse"])
def test_quiet_stretch_excursion_gaps_longest_or_refused(bump_record: tuple[Path, np.ndarray],
                                                         gaps: str) -> None:
    """--gaps longest: the stretch's fit runs over its longest piece without the excursion
    (its deviations those of that piece, numpy); --gaps refuse: no fit, the reason saying
    what to do -- as the record's own gaps."""
    rec, y = bump_record
    axes = ["gx", "gy"] if gaps == "refuse" else ["gx"]  # (gy: the same samples)
    out = AA.compute(str(rec), axes, "octave", excursions="exclude", gaps=gaps)
    r = out["axes"]["gx"]
    q = r["quiet_stretch"]
    a, b = q["excursions_excluded"]["samples"][0]
    if gaps == "refuse":
        assert not q["fitted"] and "--gaps refuse refuses gaps" in q["reason"]
        assert "--gaps skip" in q["reason"] and "adev_rad/s" not in q
        # the record's excursions: the bump on both axes, grouped as moving together
        g = [g for g in out["excursions"] if g["start_s"] < 25_300 and g["end_s"] > 25_000]
        assert len(g) == 1 and g[0]["axes"] == ["gx", "gy"]
        assert [m["axis"] for m in g[0]["members"]] == ["gx", "gy"]
        assert all(m["unit"] == "deg/h" and m["size"] > 0 for m in g[0]["members"])
        e = [e for e in r["excursions"]["excursions"] if e["start_s"] < 25_300 and e["end_s"] > 25_000]
        assert e[0]["moving_with"] == ["gy"]
        return
    qa, qb = q["samples"]
    piece = max([(qa, a), (b, qb)], key=lambda p: p[1] - p[0])
    assert q["fitted"] and q["pieces"] == [list(piece)]
    k = len(q["m"]) // 2
    assert q["adev_rad/s"][k] == pytest.approx(_pooled_oadev([y[piece[0]:piece[1]]], int(q["m"][k])),
                                               rel=1e-9)
