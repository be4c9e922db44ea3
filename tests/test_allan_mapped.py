"""rigctl allan reading samples in place (a read-only memory map of the file's chunks) gives
exactly what reading them through h5py gives, and falls back to h5py for other layouts."""
from __future__ import annotations

import numpy as np
import pytest

h5py = pytest.importorskip("h5py")

from rigctl.analysis import allan as AA  # noqa: E402

FS = 200.0


def _write(path, n: int, compression=None, rows: int = 8192) -> None:
    rng = np.random.default_rng(9)
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "rigctl-recording"
        f.attrs["schema_version"] = 1
        imu = f.create_group("imu")
        imu.attrs["sample_rate_hz"] = FS
        kw = {"chunks": (rows,), "compression": compression}
        t = imu.create_dataset("time", data=np.arange(n) / FS, **kw)
        c = imu.create_dataset("counter", data=np.arange(n, dtype=np.uint64), **kw)
        kw["chunks"] = (rows, 3)
        g = imu.create_dataset("angular_rate", data=rng.standard_normal((n, 3)) * 1e-3, **kw)
        a = imu.create_dataset("specific_force",
                               data=rng.standard_normal((n, 3)) * 1e-2 + [0, 0, 9.80665], **kw)
        t.attrs["units"], c.attrs["units"] = "s", "1"
        g.attrs["units"], a.attrs["units"] = "rad/s", "m/s^2"


def _curves(res: dict) -> dict:
    return {a: np.concatenate([r["adev_rad/s" if r["sensor"] == "gyro" else "adev_m/s^2"],
                               r["alpha"], r["edf"]]) for a, r in res["axes"].items()}


@pytest.mark.parametrize("rng_", [None, (1000, 3 * 8192 + 77)])
def test_mapped_equals_h5py(tmp_path, monkeypatch, rng_) -> None:
    path = tmp_path / "r.h5"
    n = 3 * 8192 + 1234  # a partial last chunk
    _write(path, n)
    with h5py.File(path, "r") as f:
        m = AA._MappedRows.of(str(path), f["/imu/angular_rate"])
        assert m is not None
        want = f["/imu/angular_rate"][5000:20000]
        got = np.empty_like(want)
        for r, v in m.pieces(5000, 20000):
            got[r: r + len(v)] = v
        assert np.array_equal(got, want)
    monkeypatch.setattr(AA, "CHUNK_ROWS", 5000)  # chunks not aligned with the file's
    mapped = AA.compute(str(path), list(AA.AXES), sample_range=rng_)
    monkeypatch.setattr(AA._MappedRows, "of", classmethod(lambda cls, p, d: None))
    plain = AA.compute(str(path), list(AA.AXES), sample_range=rng_)
    a, b = _curves(mapped), _curves(plain)
    assert all(np.array_equal(a[k], b[k]) for k in a)


def test_compressed_file_falls_back_to_h5py(tmp_path) -> None:
    path = tmp_path / "z.h5"
    _write(path, 20_000, compression="gzip")
    with h5py.File(path, "r") as f:
        assert AA._MappedRows.of(str(path), f["/imu/angular_rate"]) is None
    res = AA.compute(str(path), ["gx", "az"])
    assert set(res["axes"]) == {"gx", "az"}
