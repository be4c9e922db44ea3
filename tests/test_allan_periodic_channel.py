"""`rigctl allan` on a channel that repeats every 3 samples (+a, 0, -a): its Allan variance
falls as 1/tau^2 (zero, ~1e-40 by rounding, at every third tau), and the one-sided bound of a
dropped term (allan_fit._bound_fit) met an unconstrained estimate with every term below zero:
a model whose total is zero, no covariance, a singular whitener, and "internal error:
LinAlgError: singular matrix" instead of a result.
Found by a bounded search of mutated Astro Pi gyro records (`rigctl import`, then `rigctl allan
--gaps bridge`); any sample rate and gap mode showed it.

Expected value from the signal itself: at m = 1 the overlapping Allan variance is half the mean
squared first difference of the samples (a^2 for a whole number of periods)."""
from __future__ import annotations

import io
import contextlib
import json
from pathlib import Path

import numpy as np

from rigctl import cli

A = 1e-3  # rad/s


def test_a_channel_of_period_three_samples_is_analysed(tmp_path: Path) -> None:
    n, fs = 3000, 100.0
    rng = np.random.default_rng(7)
    g = rng.normal(0.0, 1e-3, (n, 3))
    g[:, 0] = np.tile([A, 0.0, -A], n)[:n]
    src = tmp_path / "p3.csv"
    src.write_text("t,gx,gy,gz\n" + "".join(
        f"{i / fs:.2f},{float(r[0])!r},{float(r[1])!r},{float(r[2])!r}\n" for i, r in enumerate(g)))
    rec = tmp_path / "p3.h5"
    assert cli.main(["import", str(src), "-o", str(rec), "--columns", "time=t,gyr_x=gx,gyr_y=gy,gyr_z=gz",
                     "--units", "gyr=rad/s,time=s"]) == 0
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = cli.main(["allan", str(rec), "--axes", "gx", "--taus", "octave", "--db", "none",
                         "--json", str(tmp_path / "p3.json")])
    assert "internal error" not in err.getvalue() and "Traceback" not in err.getvalue(), err.getvalue()
    assert code == 0, err.getvalue()
    r = json.loads((tmp_path / "p3.json").read_text())["axes"]["gx"]
    m = np.asarray(r["m"])
    adev = np.asarray(r["adev_rad/s"], dtype=float)
    want = np.sqrt(0.5 * np.mean(np.diff(g[:, 0]) ** 2))
    assert m[0] == 1 and abs(adev[0] / want - 1.0) < 1e-9, (adev[0], want)
    assert np.all(np.isfinite(adev)) and np.all(adev > 0), adev
    assert r["fit"]["coefficients"], r["fit"]
