"""`rigctl import` says the sample rate once, in one form (the new-user audit: 'imported 3000
samples at 99.99 Hz' then 'sample rate 99.990001 Hz (median step ...)' for the same rate)."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from rigctl import cli


def _csv(path: Path, t: np.ndarray | None) -> Path:
    rng = np.random.default_rng(4)
    data = rng.normal(0.0, 0.01, (t.size if t is not None else 3000, 6))
    with open(path, "w") as fh:
        fh.write(("t," if t is not None else "") + "ax,ay,az,gx,gy,gz\n")
        for i, row in enumerate(data):
            fh.write((f"{t[i]:.6f}," if t is not None else "") + ",".join(f"{v:.5f}" for v in row) + "\n")
    return path


@pytest.mark.parametrize("with_time", [True, False])
def test_the_rate_is_said_once(tmp_path: Path, capsys, with_time: bool) -> None:
    t = np.arange(3000) / 99.987 if with_time else None
    src = _csv(tmp_path / "log.csv", t)
    cols = "acc_x=ax,acc_y=ay,acc_z=az,gyr_x=gx,gyr_y=gy,gyr_z=gz" + (",time=t" if with_time else "")
    args = ["import", str(src), "-o", str(tmp_path / "log.h5"), "--columns", cols, "--units", "acc=g,gyr=deg/s"]
    assert cli.main(args + ([] if with_time else ["--rate", "100"])) == 0
    out = capsys.readouterr().out
    # the rate the import uses, from the written stamps (rounded to 6 decimals) by numpy: the
    # intervals over their span (no gaps here)
    tw = np.round(t, 6) if with_time else None
    expected = (tw.size - 1) / (tw[-1] - tw[0]) if with_time else 100.0
    rates = re.findall(r"([0-9.e+-]+) Hz", out)
    assert rates == [f"{expected:.8g}"], out
    assert out.splitlines()[0] == f"imported 3000 samples from {src}", out
