"""``rigctl allan`` on 5-minute windows of a REAL phone gyro whose curve holds a Gauss-Markov
bump (tests/data/galaxy-s5-static, Samsung Galaxy S5, 10 Hz; README there).

On gx rows 27000-30000 and 120000-123000 the fit's Gauss-Markov profile crashed with
"internal error: LinAlgError: singular matrix": an iteration of the generalized NNLS zeroed
every term, and a zero total has no covariance (rigctl/solvers/allan_fit._gls now keeps the
last iterate). The windows must now be analysed, and the bump the curve shows -- read here in
numpy, independently of rigctl -- must be the fit's Gauss-Markov term.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from recording_helpers import write_recording
from rigctl.analysis import allan as AA

FS = 10.0
WINDOWS = {"gx": (27000, 0), "gy": (120000, 0)}  # axis in the test recording: (first row, source column)
N = 3000  # 5 min at 10 Hz


def _oadev(x: np.ndarray, m: int) -> float:
    """Overlapping Allan deviation of rate samples x at tau = m / FS (plain numpy)."""
    c = np.concatenate(([0.0], np.cumsum(x)))
    d = c[2 * m:] - 2.0 * c[m:-m] + c[:-2 * m]
    return float(np.sqrt(np.mean(d ** 2) / (2.0 * m * m)))


def test_five_minute_phone_windows_with_a_bump_fit_a_gauss_markov_term(ref_data: Path,
                                                                       tmp_path: Path) -> None:
    d = ref_data / "galaxy-s5-static"
    if not d.is_dir():
        pytest.skip(f"{d} not present (AGPL-3.0 data folder left out; see its README)")
    g = np.loadtxt(d / "gyro_measured_rad_s.csv.gz", delimiter=",", skiprows=1)
    cols = {a: g[r:r + N, c] for a, (r, c) in WINDOWS.items()}
    path = write_recording(tmp_path / "phone.h5", FS,
                           angular_rate=np.column_stack((cols["gx"], cols["gy"], cols["gy"])))
    out = AA.compute(str(path), list(WINDOWS), gaps="skip")
    for a, x in cols.items():
        ms = np.arange(1, 101)
        s = np.array([_oadev(x, int(m)) for m in ms])
        top = int(np.argmax(s))
        assert s[top] > 1.3 * s[0], (a, s[0], s[top])     # the curve rises to a top: a bump
        tc_read = ms[top] / FS / 1.89   # a first-order Gauss-Markov process' ADEV peaks at 1.89 Tc
        fit = out["axes"][a]["fit"]
        gm = fit["coefficients"].gm
        assert len(gm) == 1, (a, gm)
        assert tc_read / 4 < gm[0].tau_c_s < tc_read * 4, (a, gm[0].tau_c_s, tc_read)
        assert gm[0].sigma.ci95 is not None and gm[0].sigma.ci95[0] > 0, (a, gm[0].sigma)
        assert fit["reduced_chi2"] < 2.0, (a, fit["reduced_chi2"], fit["n_taus"])
