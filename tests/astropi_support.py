"""The Astro Pi Sense HAT capture's x-up section (tests/data/astropi-sensehat-static) as a user
imports it: its rows, and a rigctl recording written by `rigctl import` from a CSV of the chosen
columns (time in s from the section's first row, whole seconds as the stamps are; a sections
file naming the one section). Shared by the Allan tests on this capture."""
from __future__ import annotations

import csv
import datetime as dt
import gzip
import json
from pathlib import Path

import numpy as np

from rigctl import cli

SET = "astropi-sensehat-static"
CSV = "astro_pi_data_20150824_085954.csv.gz"
FIRST_ROW = 3902  # the x-up section (the set's README)
#: the capture's column -> rigctl import's channel
CHANNEL = {"temp_h": "temp", "accel_x": "acc_x", "accel_y": "acc_y", "accel_z": "acc_z",
           "gyro_x": "gyr_x", "gyro_y": "gyr_y", "gyro_z": "gyr_z"}


def xup_rows(ref_data: Path) -> list[dict]:
    """The x-up section's rows, as csv.DictReader gives them."""
    with gzip.open(ref_data / SET / CSV, "rt", newline="") as fh:
        return list(csv.DictReader(fh))[FIRST_ROW:]


def seconds(rows: list[dict]) -> np.ndarray:
    """Each row's time stamp, s from the first row."""
    t0 = dt.datetime.fromisoformat(rows[0]["time_stamp"]).timestamp()
    return np.array([dt.datetime.fromisoformat(r["time_stamp"]).timestamp() - t0 for r in rows])


def import_xup(rows: list[dict], d: Path, columns: tuple[str, ...]) -> Path:
    """``rigctl import`` of ``columns`` of the rows (accelerations in g, rates in rad/s) into
    d/xup.h5; the recording's path."""
    src = d / "xup.csv"
    with src.open("w") as fh:
        fh.write(",".join(("t",) + columns) + "\n")
        for t, r in zip(seconds(rows), rows):
            fh.write(f"{t:.0f}," + ",".join(r[c] for c in columns) + "\n")
    seg = d / "sections.json"
    seg.write_text(json.dumps({"x up": {"start": 0, "end": len(rows)}}))
    rec = d / "xup.h5"
    units = ["acc=g"] if any(c.startswith("accel") for c in columns) else []
    assert cli.main(["import", str(src), "-o", str(rec), "--columns",
                     ",".join(["time=t"] + [f"{CHANNEL[c]}={c}" for c in columns]),
                     "--units", ",".join(units + ["gyr=rad/s", "time=s"]),
                     "--segments", str(seg)]) == 0
    return rec
