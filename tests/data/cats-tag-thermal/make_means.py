"""Rebuild cats_tag_60s.csv.gz from scikit-diveMove's cats_temperature_calib.nc.

    python make_means.py PATH/TO/cats_temperature_calib.nc [OUT.csv.gz]

The source file is in the wheel scikit_diveMove-0.4.0-py3-none-any.whl (PyPI) at
skdiveMove/tests/data/cats_temperature_calib.nc (sha256 below). It is netCDF-4 (HDF5), read here
with h5py, which rigctl already depends on. Output: one row per 60-s bin of the source's 1-Hz
time axis (bin k holds the samples with k*60 <= timestamp_utc < (k+1)*60), the means of the
temperature, the accelerometer and the gyro and the standard error of each mean (sample
standard deviation / sqrt(n), ddof 1), and the pose of skdiveMove's own calibration periods
(see README.md). Units as the source's: degC, m/s^2, mrad/s; t_s in s since 2021-09-20
08:52:00 UTC (the source's time origin). Deterministic: the same input gives the same bytes.
"""
from __future__ import annotations

import gzip
import hashlib
import io
import sys
from pathlib import Path

import h5py
import numpy as np

SHA256 = "24a050563f7f8f08524dec0856178ff4289ee98211085ed3462a427fe7d6cdd2"
BIN_S = 60
#: skdiveMove's periods (IMUcalibrate docstring and its test_imucalibrate.py) with axis_order
#: "zxy": the axis pointing the same way as gravity; pandas label slices, both ends included,
#: here in s since 08:52:00 (2021-09-20T09:00:00 .. 2021-09-21T10:33:00, 2021-09-21T10:40:00 ..
#: 2021-09-22T11:55:00, 2021-09-22T12:14:00 .. 2021-09-23T11:19:00)
PERIODS = [("z along gravity", 480, 92460), ("x along gravity", 92880, 183780),
           ("y along gravity", 184920, 268020)]


def main(src: str, out: str) -> None:
    raw = Path(src).read_bytes()
    if hashlib.sha256(raw).hexdigest() != SHA256:
        sys.exit(f"{src}: not the file described in README.md (sha256 differs)")
    with h5py.File(src, "r") as f:
        t = f["timestamp_utc"][()]
        assert f["timestamp_utc"].attrs["units"] == b"seconds since 2021-09-20 08:52:00"
        assert f["angular_velocity"].attrs["units"] == b"mrad/s"
        assert f["acceleration"].attrs["units"] == b"m/s2"
        T = f["temperature"][()]
        acc = f["acceleration"][()]
        gyr = f["angular_velocity"][()]
    assert np.all(np.diff(t) == 1) and t[0] == 0
    k = t // BIN_S
    n = np.bincount(k)
    rows = []
    for b in range(n.size):
        sl = slice(int(np.searchsorted(k, b)), int(np.searchsorted(k, b, side="right")))
        m = sl.stop - sl.start
        start = b * BIN_S
        pose = next((p for p, a, z in PERIODS if a <= start and start + BIN_S - 1 <= z), "")
        vals = [T[sl], *acc[sl].T, *gyr[sl].T]
        mean = [float(v.mean()) for v in vals]
        se = [float(v.std(ddof=1) / np.sqrt(m)) if m > 1 else float("nan") for v in vals]
        rows.append((start, m, mean, se, pose))
    buf = io.StringIO()
    buf.write("t_s,n,temp_c,acc_x,acc_y,acc_z,gyr_x,gyr_y,gyr_z,"
              "se_temp_c,se_acc_x,se_acc_y,se_acc_z,se_gyr_x,se_gyr_y,se_gyr_z,pose\n")
    for start, m, mean, se, pose in rows:
        buf.write(f"{start},{m}," + ",".join(f"{v:.7g}" for v in mean) + ","
                  + ",".join(f"{v:.4g}" for v in se) + f",{pose}\n")
    with open(out, "wb") as fh:  # gzip with no name and mtime 0: reproducible bytes
        with gzip.GzipFile(filename="", mode="wb", fileobj=fh, compresslevel=9, mtime=0) as gz:
            gz.write(buf.getvalue().encode())


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else str(Path(__file__).with_name("cats_tag_60s.csv.gz")))
