"""The CATS tag record held still in three poses (tests/data/cats-tag-thermal) as a user imports
it: its rows, and a rigctl recording written by ``rigctl import`` from the stored .csv.gz, with
the pose column as sections or without it. Shared by the thermal tests on this record."""
from __future__ import annotations

import csv
import gzip
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from helpers import run_rigctl

SET = "cats-tag-thermal"
CSV = "cats_tag_60s.csv.gz"
SHA256 = "6be37b416b36f489e89501cddbfc8a21a432786b3d05f8ee74bde947e44f4187"
POSES = ["z along gravity", "x along gravity", "y along gravity"]
COLUMNS = "time=t_s,temp=temp_c,acc_x=acc_x,acc_y=acc_y,acc_z=acc_z,gyr_x=gyr_x,gyr_y=gyr_y,gyr_z=gyr_z"
UNITS = "acc=m/s^2,gyr=mrad/s,time=s"
WINDOW_ROWS = 30  # 30 min of 60-s means
MRAD = 1e-3


def folder(ref_data: Path) -> Path:
    """The data folder; the test skips, naming it, when it has been left out."""
    d = ref_data / SET
    if not (d / CSV).is_file():
        pytest.skip(f"{d} not present (AGPL-3.0 data: a redistribution may leave it out, see its README)")
    return d


def rows(ref_data: Path) -> list[dict[str, str]]:
    """The CSV's rows (its sha256 checked), as csv.DictReader gives them."""
    raw = (folder(ref_data) / CSV).read_bytes()
    assert hashlib.sha256(raw).hexdigest() == SHA256
    return list(csv.DictReader(gzip.decompress(raw).decode().splitlines()))


def import_record(ref_data: Path, out: Path, sections: bool = True) -> Path:
    """``rigctl import`` of the stored .csv.gz into ``out``; ``sections``: the pose column as the
    recording's sections, else one section of kind capture over all 4469 rows (a log whose poses
    nobody marked)."""
    cols = COLUMNS + (",section=pose" if sections else "")
    more: list[str] = []
    if not sections:
        seg = out.with_suffix(".segments.json")
        seg.write_text(json.dumps([{"label": "record", "start": 0, "end": 4469, "kind": "capture"}]))
        more = ["--segments", str(seg)]
    proc = run_rigctl("import", str(folder(ref_data) / CSV), "-o", str(out), "--columns", cols, "--units", UNITS,
                      *more)
    assert proc.returncode == 0, proc.stderr
    return out


def numpy_windows(rows: list[dict[str, str]], skip_rows: int = 0) -> dict[str, np.ndarray]:
    """Per pose, consecutive chunks of 30 rows from its first row (after ``skip_rows``); a last
    chunk kept with at least 16 rows (the application layer's rule for a window of 30
    samples)."""
    pose = np.array([r["pose"] for r in rows])
    T = np.array([float(r["temp_c"]) for r in rows])
    gyr = np.array([[float(r[f"gyr_{a}"]) for a in "xyz"] for r in rows]) * MRAD
    acc = np.array([[float(r[f"acc_{a}"]) for a in "xyz"] for r in rows])
    t = np.array([float(r["t_s"]) for r in rows])
    chunks, labels = [], []
    for p in POSES:
        idx = np.flatnonzero(pose == p)[skip_rows:]
        for s in range(0, idx.size, WINDOW_ROWS):
            c = idx[s:s + WINDOW_ROWS]
            if c.size >= 16:
                chunks.append(c)
                labels.append(p)
    down = {p: acc[pose == p].mean(axis=0) for p in POSES}
    return {"chunks": chunks, "pose": np.array(labels), "k": np.array([POSES.index(p) for p in labels]),
            "T": np.array([T[c].mean() for c in chunks]),
            "p1": np.array([np.mean(T[c] - 25.0) for c in chunks]),
            "p2": np.array([np.mean((T[c] - 25.0) ** 2) for c in chunks]),
            "rate_K_h": np.array([np.polyfit(t[c] - t[c][0], T[c], 1)[0] * 3600.0 for c in chunks]),
            "gyr": np.array([gyr[c].mean(axis=0) for c in chunks]),
            "acc": np.array([acc[c].mean(axis=0) for c in chunks]),
            "down": down, "se_gyr": np.array([[float(r[f"se_gyr_{a}"]) for a in "xyz"] for r in rows]) * MRAD,
            "n": np.array([int(r["n"]) for r in rows]), "row_pose": pose}
