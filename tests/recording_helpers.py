"""A minimal valid recording written by hand with h5py, from the recorder's own constants.

For tests that need a recording of given samples without running the engine: the root
attributes (:data:`rigctl.recording.recorder.FORMAT_NAME`, :data:`~rigctl.recording.recorder.SCHEMA_VERSION`, the
rigctl version), ``/run/status``, ``/imu`` with its sample rate, and optional ``/pulses`` and
``/truth``, each dataset with the units :data:`rigctl.recording.recorder.LAYOUT` gives it. The data keep
the dtype they are given (a test may store float32 on purpose).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import h5py
import numpy as np

from rigctl import __version__
from rigctl.recording import recorder


def _group(f: h5py.File, name: str, columns: dict[str, Any], chunk_rows: int | None = None) -> h5py.Group:
    g = f.require_group(name)
    for key, data in columns.items():
        data = np.asarray(data)
        chunks = (min(chunk_rows, len(data)), *data.shape[1:]) if chunk_rows and len(data) else None
        d = g.create_dataset(key, data=data, chunks=chunks)
        d.attrs["units"] = recorder.LAYOUT[name][key][2]
    return g


def write_recording(path: Path, rate_hz: float, *, counter: np.ndarray | None = None, n: int | None = None,
                    status: str = "complete", chunk_rows: int | None = None,
                    pulses: dict[str, Any] | None = None, truth_json: str | None = None,
                    **imu: Any) -> Path:
    """Write ``path``: /imu at ``rate_hz`` with the columns given as keywords (angular_rate,
    specific_force, temperature); ``counter`` (default 0..n-1, n from the first column) and
    ``time`` = counter / rate_hz unless given; ``pulses``: /pulses columns; ``truth_json``:
    /truth params_json; ``chunk_rows``: HDF5 chunk rows of the /imu datasets."""
    if counter is None:
        n = n if n is not None else len(next(iter(imu.values())))
        counter = np.arange(n, dtype=np.uint64)
    imu.setdefault("time", np.asarray(counter, dtype=float) / rate_hz)
    with h5py.File(path, "w") as f:
        f.attrs.update({"format": recorder.FORMAT_NAME, "schema_version": recorder.SCHEMA_VERSION,
                        "rigctl_version": __version__})
        f.create_dataset("run/status", data=np.array([status.encode()], dtype=recorder.STATUS_DTYPE))
        g = _group(f, "imu", {"time": imu.pop("time"), "counter": counter, **imu}, chunk_rows)
        g.attrs["sample_rate_hz"] = float(rate_hz)
        if pulses is not None:
            _group(f, "pulses", pulses)
        if truth_json is not None:
            f.require_group("truth").attrs["params_json"] = truth_json
    return path
